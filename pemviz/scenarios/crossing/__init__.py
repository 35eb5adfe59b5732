"""The crossing scenario (an ego car, a pedestrian crossing, an emergency brake on tracked pedestrians), one
package: the scene (:mod:`~pemviz.scenarios.crossing.scene`), built only from :mod:`pemviz.stack`, and its problem
(:mod:`~pemviz.scenarios.crossing.problem`)."""
