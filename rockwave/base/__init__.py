"""Lowest layer: errors, the solver contract, devices, small maths and atomic files. Imports nothing of rockwave."""
