"""The viser panel of ``pemviz serve`` (:class:`pemviz.app.panel.PanelApp`, one :class:`pemviz.app.session.Session`
per browser client).

Run bookkeeping in :mod:`pemviz.app.runs`, the form in :mod:`pemviz.app.form`, what the panel asks of a scenario's
drawing object in :mod:`pemviz.app.drawing`, the figures in :mod:`pemviz.app.plots`. Nothing is imported here: each
name has one import path, its module's (``from pemviz.app.panel import PanelApp, serve``).
"""
