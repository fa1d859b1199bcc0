"""polycc: certified polytope obstacle covers from 3D Gaussian Splatting scenes for Crazyflie firmware."""

__version__ = "0.1.0"
