"""pointfence: haptic virtual fixtures from streaming depth cameras."""
__version__ = "0.1.0"
