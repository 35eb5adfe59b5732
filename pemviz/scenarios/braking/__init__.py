"""The automated-braking scenario of Innes & Ramamoorthy (2022), one package: the simulator and its parameters
(:mod:`~pemviz.scenarios.braking.simulator`), its batched twin, problem, exact answers
(:mod:`~pemviz.scenarios.braking.truth` and its siblings), a failure's story
(:mod:`~pemviz.scenarios.braking.failures`) and its drawing. Nothing is imported here."""
