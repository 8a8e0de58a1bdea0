"""The simulated clock as the X-ray grabbers see it: frames are released only once a world step is complete."""
from __future__ import annotations

import threading

from appliance.sim_bench import SimClock


def test_released_clock_stands_still_while_the_world_steps_and_then_wakes_the_grabbers() -> None:
    clock = SimClock()
    woke: list[float] = []
    sleeper = threading.Thread(target=lambda: (clock.sleep(10.0), woke.append(clock.released())))
    with clock.hold():
        sleeper.start()
        clock.advance(4.0)
        clock.advance(6.0)
        assert clock.now() == 10.0
        assert clock.released() == 0.0      # mid-step: a grabber still sees the step's start
        sleeper.join(timeout=0.2)
        assert sleeper.is_alive() and not woke
    sleeper.join(timeout=5.0)
    assert woke == [10.0]                    # released at the end of the step, in simulated time
    clock.advance(0.5)                       # outside a step the released clock follows at once
    assert clock.released() == clock.released_now() == 10.5


def test_nested_holds_release_once_at_the_outermost_end() -> None:
    clock = SimClock(1.0)
    with clock.hold():
        with clock.hold():
            clock.advance(1.0)
        assert clock.released() == 1.0
    assert clock.released() == 2.0
