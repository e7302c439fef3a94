import os

# Four CPU devices for the data-parallel tests (test_distributed.py); set before JAX
# starts. Every other test runs on device 0 alone, as before.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()

import physgrad  # noqa: E402,F401  (enables float64 before any test builds arrays)
