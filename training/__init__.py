"""Training side: data, simulation, models, MLflow tracking, evaluation and ONNX export."""
