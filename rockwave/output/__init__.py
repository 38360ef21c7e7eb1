"""What a run writes: recorders (USD, VTK, CSV), the fluid surface and the hazard summary. Reads the simulation only."""
