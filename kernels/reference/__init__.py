"""The NumPy reference backend: the executable specification every backend is tested against."""
