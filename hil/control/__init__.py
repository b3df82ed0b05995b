"""Estimators and controllers of the seed papers: pure per-sample building blocks on plain floats.

Each class has a ``step(...)`` that costs microseconds (the 1 kHz hot path), explicit units, and a
docstring citing the equations it implements and how it was discretised.
"""
