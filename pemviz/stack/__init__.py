"""A realistic perception stack as library pieces, for any scene: the camera (:mod:`pemviz.stack.camera`), a noisy
detector on the shipped PEMs (:mod:`pemviz.stack.detector`) and a batched constant-velocity Kalman tracker
(:mod:`pemviz.stack.tracker`); a scene of one's own writes only its geometry and controller on them
(``docs/realistic-stack.md``). Importing the package loads none of its modules."""
