"""A realistic perception stack as library pieces, for any scene: what a camera sees of each object and where it
measures it (:mod:`pemviz.stack.camera`), a noisy detector on the shipped PEMs with the log-probabilities of its
detections and the log-densities of its errors kept apart (:mod:`pemviz.stack.detector`), and a constant-velocity
Kalman tracker with gating, confirmation, dropping and restart, batched over rollouts (:mod:`pemviz.stack.tracker`).
A scene of one's own writes only its geometry and its controller on them (the guide's *A realistic perception stack*,
``docs/realistic-stack.md``). Importing the package loads none of its modules."""
