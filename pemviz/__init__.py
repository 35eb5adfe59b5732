"""pemviz: rare-failure estimation for perception-driven controllers with perception error models (PEMs)
and adaptive importance sampling (Innes & Ramamoorthy 2022), with rerun and viser views."""

import os as _os

__version__ = "0.1.0"

# The same digits on every x86-64 machine: a run's proposal fits amplify the last bit of every matrix product, and
# Intel MKL (torch's BLAS) picks its kernels per CPU unless told a branch (its "conditional numerical reproducibility",
# read at MKL's first call: set before pemviz or anything else runs torch). AVX2 runs on every x86-64 CPU of the last
# decade; set MKL_CBWR yourself to choose another branch.
_os.environ.setdefault("MKL_CBWR", "AVX2")

try:  # the gymnasium environment pemviz/Braking-v0, registered by entry-point string (no simulator import)
    from pemviz.envs import register_envs as _register_envs
except ImportError:  # gymnasium absent: everything but the environment still works
    pass
else:
    _register_envs()
