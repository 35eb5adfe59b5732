"""The core: the small typed pieces every run is made of, with no I/O beyond saving and loading its own models
(``docs/layout.md`` names each module). Nothing is imported here: each module by its own name."""
