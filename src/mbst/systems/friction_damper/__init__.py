"""Banded rotary friction damper: imposed displacement, measured friction force."""
