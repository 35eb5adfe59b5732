"""The cut-in scenario, one package: its parameters, names, controller and rule
(:mod:`~pemviz.scenarios.cut_in.scenario`), the geometry of each step (:mod:`~pemviz.scenarios.cut_in.scene`), the
tracker it builds on (:mod:`pemviz.stack.tracker`, scene-neutral), the simulator on highway-env vehicles
(:mod:`~pemviz.scenarios.cut_in.highway`), its batched twin (:mod:`~pemviz.scenarios.cut_in.batched`), its problem
(:mod:`~pemviz.scenarios.cut_in.problem`), a rollout's story (:mod:`~pemviz.scenarios.cut_in.story`) and its drawing
(:mod:`~pemviz.scenarios.cut_in.drawing`, with :mod:`~pemviz.scenarios.cut_in.recording` and
:mod:`~pemviz.scenarios.cut_in.panel`). Nothing is imported here: each name has one import path, its module's."""
