"""Measurement results: one directory per measurement (temp dir + rename), figure, Mitsuba medium."""

from trimeter.results.writer import Parameters, write_measurement

__all__ = ["Parameters", "write_measurement"]
