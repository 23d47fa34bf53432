"""mmpa: precise mobile manipulation with a MuJoCo digital twin."""

__version__ = "0.1.0"
