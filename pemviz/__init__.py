"""pemviz: rare-failure estimation for perception-driven controllers with perception error models (PEMs)
and adaptive importance sampling (Innes & Ramamoorthy 2022), with rerun and viser views."""

__version__ = "0.1.0"

try:  # the gymnasium environment pemviz/Braking-v0, registered by entry-point string (no simulator import)
    from pemviz.envs import register_envs as _register_envs
except ImportError:  # gymnasium absent: everything but the environment still works
    pass
else:
    _register_envs()
