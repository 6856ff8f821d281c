"""Comparison reports: methods, renders, metrics, figures and the HTML page of ``compare``/``bench``."""
