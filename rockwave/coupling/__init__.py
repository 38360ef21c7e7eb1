"""Water meets rock: penalty forces between particles and block faces, Adami wall particles on moving blocks."""
