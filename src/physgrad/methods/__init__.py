"""Update rules, one file each: the direction (a rule), its public entry point, and what
the engine runs (a method: rule + optax transformation).

=====================  ===============================  =====================================
entry point            rule                             direction
=====================  ===============================  =====================================
:func:`dp`             :class:`Gradient`                ∇_θ L (DP)
:func:`gauss_newton`   :class:`JacobianPower` (κ = −1)  J⁺ g
:func:`hig`            :class:`JacobianPower` (κ = −½)  V Σ^{−½} Uᵀ g
:func:`kronecker_hig`  :class:`KroneckerPower`          b^{−p} G^p ∇W A^p per dense layer
(method)               :class:`LevenbergMarquardt`      Jᵀ(J Jᵀ + λI)⁻¹ g, λ adapted per step
:func:`newton`         :class:`Newton`                  (H + λI)⁻¹ ∇L
:func:`sip`            :class:`ScaleInvariantPhysics`   ∇_θ ½‖x − x̃‖², x̃ from a local inverse
:func:`bptt`           :class:`RolloutGradient`         rollout gradient under a policy
:func:`stabilised_bptt` :class:`RolloutGradient`        M's gradient masked by R's signs
:func:`unrolled`       :class:`UnrolledGradient`        ONE / NOG / WIG gradients
=====================  ===============================  =====================================

Each rule declares the part of a problem's :class:`Objective` it uses (:class:`Part`):
:data:`OPEN_LOOP` (``predict``, ``loss``: DP, Gauss–Newton, HIG, LM, Newton, K-FAC, KHIG),
:data:`SPLIT` (``network_output``, ``simulate``, ``target``, optional ``inverse``: SIP),
:data:`ROLLOUT` (a rollout system: BPTT and its variants) or :data:`UNROLLED` (a
time-stepper's windows: ONE / NOG / WIG); its ``check`` refuses a problem without it.

What the engine runs is a rule with an optax transformation, optionally an acceptance test
that may refuse a step (:mod:`physgrad.acceptance`) and a control that hands the rule a
value from the state (:class:`AbstractControl`): :class:`AbstractOptaxMethod` implements
it once, and :class:`Method`, :class:`LevenbergMarquardt` (:class:`GainRatio` with the
:class:`Damping` control), :class:`Unrolled`, :class:`AveragedKronecker` (KHIG with
K-FAC's running factors, :class:`RunningFactors`) and :class:`EigenCorrectedKronecker` (KHIG's
eigenbasis with the exact Gauss–Newton diagonal, :class:`KeptEigenbasis`) are its final classes, which only fill
its fields; :func:`LossAwareDP` is a constructor of a :class:`Method`. The registry of names for the
command line is :mod:`physgrad.harness.registry`.
"""

from .averaged_kronecker import AveragedKronecker, RunningFactors
from .base import (
    OPEN_LOOP,
    ROLLOUT,
    SPLIT,
    UNROLLED,
    AbstractJacobianRule,
    AbstractMethod,
    AbstractRule,
    Estimator,
    Objective,
    Part,
    Stepper,
    trainable,
)
from .dp import Gradient, LossAwareDP, dp
from .eigen_kronecker import EigenCorrectedKronecker, KeptEigenbasis
from .hig import JacobianPower, gauss_newton, hig
from .kronecker_hig import KroneckerPower, kronecker_hig
from .lm import Damping, GainRatio, LevenbergMarquardt, adapt_damping, levenberg_marquardt, predicted_decrease
from .method import AbstractControl, AbstractOptaxMethod, Method, MethodState
from .newton import Newton, newton
from .sip import AbstractProxy, L1Proxy, L2Proxy, ScaleInvariantPhysics, sip
from .stable_bptt import RolloutGradient, bptt, stabilised_bptt
from .unrolling import Unrolled, UnrolledGradient, schedule, unrolled

__all__ = [
    "AbstractControl",
    "AbstractJacobianRule",
    "AbstractMethod",
    "AbstractOptaxMethod",
    "AbstractProxy",
    "AbstractRule",
    "AveragedKronecker",
    "Damping",
    "EigenCorrectedKronecker",
    "Estimator",
    "GainRatio",
    "Gradient",
    "JacobianPower",
    "KeptEigenbasis",
    "KroneckerPower",
    "L1Proxy",
    "L2Proxy",
    "LevenbergMarquardt",
    "LossAwareDP",
    "Method",
    "MethodState",
    "Newton",
    "Objective",
    "OPEN_LOOP",
    "Part",
    "Stepper",
    "ROLLOUT",
    "SPLIT",
    "UNROLLED",
    "RolloutGradient",
    "RunningFactors",
    "ScaleInvariantPhysics",
    "Unrolled",
    "UnrolledGradient",
    "adapt_damping",
    "bptt",
    "dp",
    "gauss_newton",
    "hig",
    "kronecker_hig",
    "levenberg_marquardt",
    "newton",
    "predicted_decrease",
    "schedule",
    "sip",
    "stabilised_bptt",
    "trainable",
    "unrolled",
]
