"""hilsim: a hardware-in-the-loop bridge for autonomous underwater vehicles."""

__version__ = "0.1.0"
