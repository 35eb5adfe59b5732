"""pemviz: rare-failure estimation for perception-driven controllers with perception error models (PEMs)
and adaptive importance sampling (Innes & Ramamoorthy 2022), with rerun and viser views."""

__version__ = "0.1.0"
