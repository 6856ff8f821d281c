"""Comparison reports: methods, renders, metrics, figures and the HTML page of ``compare``/``bench``."""

import os

#: Where ``compare`` and ``bench`` keep their converged reference images (``--cache-dir``).
DEFAULT_CACHE_DIR = os.path.join(os.path.expanduser("~"), ".cache", "mitsuba-shsampling")
