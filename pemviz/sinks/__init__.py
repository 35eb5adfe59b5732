"""Sinks: listeners of the experiment engine's events (console table, rerun recording, viser panel).

A sink only listens; it never drives the engine (the viser panel may set the cancel token).
"""
