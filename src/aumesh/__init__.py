"""aumesh: AU(+pose) -> MediaPipe FaceMesh PLS, reproducible and fast."""

__version__ = "0.1.0"
