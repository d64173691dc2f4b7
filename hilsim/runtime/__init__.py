"""Runtime: clocks, the scheduler of periodic events, and (later) the bridge."""

from hilsim.runtime.clock import Clock, RealTimeClock, VirtualClock
from hilsim.runtime.scheduler import DEFAULT_PHYSICS_RATE, EventStats, PeriodicEvent, Scheduler, VehicleLoop

__all__ = ["Clock", "RealTimeClock", "VirtualClock", "Scheduler", "PeriodicEvent", "EventStats",
           "VehicleLoop", "DEFAULT_PHYSICS_RATE"]
