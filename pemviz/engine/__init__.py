"""The engine: runs an estimator's stages on a problem and emits events (:mod:`pemviz.engine.experiment`), with the
events (:mod:`pemviz.engine.events`), the cost model (:mod:`pemviz.engine.cost`), memory and CPUs
(:mod:`pemviz.engine.resources`) and executors (:mod:`pemviz.engine.executors`). Nothing is imported here;
``events``, ``cost`` and ``resources`` import neither the experiment nor torch. Constants such as ``STREAM_ABOVE``
are set on :mod:`pemviz.engine.experiment`."""
