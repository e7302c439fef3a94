import os

# Four CPU devices for the data-parallel tests (test_distributed.py); set before JAX
# starts. Every other test runs on device 0 alone, as before.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()

import jax  # noqa: E402

# The test session enables float64 itself (importing physgrad does not): the reference
# tests compare against NumPy float64 to 1e-7 and build float64 problems, as equinox's and
# diffrax's own test suites do. tests/test_side_effects.py checks, in fresh interpreters,
# that physgrad works with x64 off and leaves the setting alone.
jax.config.update("jax_enable_x64", True)
