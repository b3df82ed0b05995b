"""hil: hardware-in-the-loop bench for airborne electro-optical stabilized platforms."""

__version__ = "0.1.0"
