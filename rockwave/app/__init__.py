"""What users run: the run loop, progress, the command line, scenario sweeps, preview and plot."""
