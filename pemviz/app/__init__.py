"""The viser panel of ``pemviz serve`` (:class:`pemviz.app.panel.PanelApp`, one :class:`pemviz.app.session.Session`
per browser client): runs in :mod:`pemviz.app.runs`, the form in :mod:`pemviz.app.form`, the drawing hooks in
:mod:`pemviz.app.drawing`, the figures in :mod:`pemviz.app.plots`. Nothing is imported here."""
