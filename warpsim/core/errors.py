"""Errors raised while simulating."""


class SimulationError(RuntimeError):
    """The simulation blew up (non-finite values or speeds beyond the bound).

    Attributes: ``step`` (steps taken when detected), ``time`` [s], ``particle`` (index of the
    first offending particle or coordinate), ``frame`` (set by ``Simulator.run``, else None)."""

    def __init__(self, message: str, step: int, time: float, particle: int, frame=None):
        super().__init__(message)
        self.step, self.time, self.particle, self.frame = step, time, particle, frame
