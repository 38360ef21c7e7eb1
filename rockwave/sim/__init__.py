"""A scene made runnable: the clock, the block sub-stepping policy, Simulation, readers, checkpoints, the guard and
the MPI simulation."""
