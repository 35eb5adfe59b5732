"""pemviz's files: the logged-rollout format (:mod:`~pemviz.io.rollout_format`, :mod:`~pemviz.io.rollouts`), the
estimate from a rollout file (:mod:`~pemviz.io.rollout_estimate`), safe writes and output-path checks
(:mod:`~pemviz.io.files`) and the KITTI salient data (:mod:`~pemviz.io.data`). The core does no I/O; a model's own
files are saved beside it (:func:`pemviz.pem.save_pem`, :func:`pemviz.core.sampling.save_proposal`)."""
