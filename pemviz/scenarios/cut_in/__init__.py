"""The cut-in scenario, one package: parameters, names, controller and rule
(:mod:`~pemviz.scenarios.cut_in.scenario`), each step's geometry (:mod:`~pemviz.scenarios.cut_in.scene`), the
highway-env simulator and its batched twin (:mod:`~pemviz.scenarios.cut_in.highway`,
:mod:`~pemviz.scenarios.cut_in.batched`), its problem, story and drawing. Nothing is imported here."""
