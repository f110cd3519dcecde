"""The application layer: configs in, run directories out (commands that the CLI calls).

Modules here turn a config into work for the library below and write what a
run leaves behind; the library never sees a config. :mod:`.sweep`: a grid of
configs fitted into one run directory.
"""
