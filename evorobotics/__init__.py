"""The science of the paper as pure numpy: controller network, GA, maze simulator, fitness.

No I/O and no network: the same code evaluates a controller in simulation and runs it on a
robot. Exception root: `EvoError` (see `evorobotics.errors`).
"""
