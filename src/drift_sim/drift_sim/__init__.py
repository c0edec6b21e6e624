"""Plant simulator of the drift stack: a double-track car richer than the controller model."""
