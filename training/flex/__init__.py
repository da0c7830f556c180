"""Joint angles from flex and capacitive sensors (Chen et al. 2024): simulation, models, evaluation, export."""
