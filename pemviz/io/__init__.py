"""pemviz's files: the logged-rollout format (:mod:`~pemviz.io.rollout_format`, :mod:`~pemviz.io.rollouts`), the
estimate from a rollout file (:mod:`~pemviz.io.rollout_estimate`: ``pemviz estimate``), safe writes and output-path
checks (:mod:`~pemviz.io.files`) and the KITTI salient data (:mod:`~pemviz.io.data`).

The core (PEM, STL, scenarios, sampler) does no I/O; what reads or writes a file lives here or beside the model it
stores (:func:`pemviz.pem.save_pem`, :func:`pemviz.core.sampling.save_proposal`).
"""
