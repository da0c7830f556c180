"""Pure numpy/scipy domain code shared by training and the service (DESIGN.md §1)."""
