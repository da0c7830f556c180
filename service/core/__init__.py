"""Pure numpy/scipy domain code shared by training and the service (docs/conventions.md)."""
