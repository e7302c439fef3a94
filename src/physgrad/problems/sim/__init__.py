"""The simulators' support the problems are built on: a staggered-grid fluid solver
(:mod:`fluid`), PhiFlow adapters (:mod:`phiflow`), time-stepper solvers and their
composition (:mod:`steppers`), explicit integrators (:mod:`integrators`) and the dataset
cache (:mod:`cache`)."""

from . import cache, fluid, integrators, phiflow, steppers

__all__ = ["cache", "fluid", "integrators", "phiflow", "steppers"]
