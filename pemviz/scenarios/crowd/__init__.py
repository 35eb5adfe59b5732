"""The crowd toy (several obstacles, each detected and mislocated), one package: the model, its detector, batched
twin and closed-form answer (:mod:`~pemviz.scenarios.crowd.simulator`) and its problem
(:mod:`~pemviz.scenarios.crowd.problem`). Nothing is imported here: each name has one import path, its module's."""
