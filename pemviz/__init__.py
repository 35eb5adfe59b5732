"""pemviz: rare-failure estimation for perception-driven controllers with perception error models (PEMs)
and adaptive importance sampling (Innes & Ramamoorthy 2022), with rerun and viser views."""

import importlib.abc as _abc
import importlib.machinery as _machinery
import importlib.util as _util
import os as _os
import sys as _sys
import types as _types

__version__ = "0.1.0"

# The same digits on every x86-64 machine: a run's proposal fits amplify the last bit of every matrix product, and
# Intel MKL (torch's BLAS) picks its kernels per CPU unless told a branch (its "conditional numerical reproducibility",
# read at MKL's first call: set before pemviz or anything else runs torch). AVX2 runs on every x86-64 CPU of the last
# decade; set MKL_CBWR yourself to choose another branch.
_os.environ.setdefault("MKL_CBWR", "AVX2")


def _register_env() -> None:
    """Register the gymnasium environment pemviz/Braking-v0 by entry-point string (no simulator import)."""
    try:
        from pemviz.envs import register_envs
    except ImportError:  # gymnasium absent (everything but the environment still works), or pemviz.envs is the module
        return  # importing gymnasium: it registers the environment itself once it is defined
    register_envs()


class _RegisterWhenGymnasiumLoads(_abc.MetaPathFinder):
    """Registers the environment right after gymnasium is imported, so ``import pemviz`` does not import gymnasium:
    a finder that, asked once for gymnasium, takes itself off ``sys.meta_path`` and hands back gymnasium's own spec
    with the registration after its ``exec_module``."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> _machinery.ModuleSpec | None:
        if name != "gymnasium":
            return None
        _sys.meta_path.remove(self)
        spec = _util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        exec_module = spec.loader.exec_module

        def exec_then_register(module: _types.ModuleType) -> None:
            exec_module(module)
            _register_env()

        spec.loader.exec_module = exec_then_register  # type: ignore[method-assign]
        return spec


if "gymnasium" in _sys.modules:
    _register_env()
else:
    _sys.meta_path.insert(0, _RegisterWhenGymnasiumLoads())
