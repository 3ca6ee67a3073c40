"""What the multi-hand and multi-host tests share: a short grasp and the tracking target."""
from __future__ import annotations

#: a grasp that fits 2 s of sim time: close over 0.1 … 0.9 s, hold 0.2 s, open over 1.1 … 1.9 s;
#: the other two fingers open (so every finger has an excursion to be scored against)
SHORT_GRASP = dict(t_start=0.1, t_close=0.8, t_hold=0.2, t_open=0.8, others='open')
DURATION = 2.0
#: the free-space tracking target: RMSE <= 5 % of each finger's peak excursion
TARGET_PCT = 5.0


def worst_pct(fingers: dict) -> float:
    """The largest free-space RMSE of a report's fingers, as % of its excursion."""
    return max(f['rmse_pct'] for f in fingers.values())
