"""HTTP layer: schemas, routes and error mapping."""
