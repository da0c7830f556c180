"""Model loading (manifest-checked) and onnxruntime inference."""
