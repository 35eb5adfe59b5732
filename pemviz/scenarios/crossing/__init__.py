"""The crossing scenario (an ego car, a pedestrian crossing, an emergency brake on tracked pedestrians), one package:
the scene (:mod:`~pemviz.scenarios.crossing.scene`), built only from the library's perception stack
(:mod:`pemviz.stack`), and its problem (:mod:`~pemviz.scenarios.crossing.problem`). Each name has one import path,
its module's."""
