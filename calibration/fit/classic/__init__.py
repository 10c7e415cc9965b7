"""Classic parametric models (OpenCV families) and their closed-form estimators."""
