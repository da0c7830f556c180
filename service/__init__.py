"""Inference service and the shared domain code (``service.core``) that training imports too."""
