"""The automated-braking scenario of Innes & Ramamoorthy (2022), one package: the simulator on highway-env vehicles
and its parameters (:mod:`~pemviz.scenarios.braking.simulator`), its batched twin
(:mod:`~pemviz.scenarios.braking.batched`), its problem (:mod:`~pemviz.scenarios.braking.problem`), its exact answers
(:mod:`~pemviz.scenarios.braking.truth`, with :mod:`~pemviz.scenarios.braking.truth_cells`,
:mod:`~pemviz.scenarios.braking.truth_latched` and :mod:`~pemviz.scenarios.braking.truth_known`), a failure's story
(:mod:`~pemviz.scenarios.braking.failures`) and its drawing (:mod:`~pemviz.scenarios.braking.drawing`, with
:mod:`~pemviz.scenarios.braking.recording` and :mod:`~pemviz.scenarios.braking.panel`). Nothing is imported here:
each name has one import path, its module's."""
