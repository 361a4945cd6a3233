"""`trimeter bench twin`: the benchmark lives beside the twin it measures."""

from trimeter.twin.bench import register

__all__ = ["register"]
