"""Studies that run pemviz many times and report: against exact answers (:mod:`~pemviz.studies.validation`,
``pemviz validate``), the paper's tables and figure (:mod:`~pemviz.studies.paper_tables`, ``pemviz tables``) and the
PEMs' quality (:mod:`~pemviz.studies.pem_eval` and, for the noise PEMs, :mod:`~pemviz.studies.noise_eval`, ``pemviz pem
eval``). Nothing in the core imports them."""
