"""12-speed automated manual transmission (AMT): ratios, shift schedule and the timing of a shift.

A shift interrupts traction: the engine ramps its brake torque down (`RAMP_DOWN_S`), the clutch opens and the
engine synchronises to the new gear's speed in neutral (`NEUTRAL_S`), then the clutch closes and the torque
ramps back up (`RAMP_UP_S`). ETC2 reports the selected gear at once, the current gear as 0 while in neutral.
"""

GEAR_RATIOS = (11.32, 9.16, 7.19, 5.82, 4.58, 3.70, 3.09, 2.50, 1.96, 1.58, 1.25, 1.00)
"""Gear ratios i_gear of gears 1..12 (direct top gear, range-change and splitter box)."""

RAMP_DOWN_S = 0.25
NEUTRAL_S = 0.45
RAMP_UP_S = 0.30
SHIFT_S = RAMP_DOWN_S + NEUTRAL_S + RAMP_UP_S
MIN_GEAR_HOLD_S = 1.0
"""No new shift within this time [s] after a shift ends (hunting protection)."""

CLUTCH_OPEN_RPM = 680.0
"""Below this engine speed [rpm] in gear with no driving demand the clutch opens (engine to idle)."""


def upshift_rpm(pedal: float) -> float:
    """Engine speed [rpm] above which the AMT shifts up; later at a deeper pedal (0..1)."""
    return 1250.0 + 450.0 * pedal


def downshift_rpm(pedal: float) -> float:
    """Engine speed [rpm] below which the AMT shifts down; earlier at a deeper pedal (0..1)."""
    return 880.0 + 320.0 * pedal


def select_gear(gear: int, rpm_per_m_s: list, speed_m_s: float, pedal: float) -> int:
    """The gear the shift logic wants (1..12) given the current gear and vehicle speed.

    rpm_per_m_s[g-1]: engine speed per unit vehicle speed in gear g [rpm/(m/s)]. Up: the highest gear at most
    two steps up whose speed stays above the down threshold + 150 rpm. Down (not below gear 2): the first gear,
    at most two steps down, whose speed reaches the down threshold + 250 rpm.
    """
    rpm = speed_m_s * rpm_per_m_s[gear - 1]
    if rpm > upshift_rpm(pedal) and gear < len(GEAR_RATIOS):
        floor = downshift_rpm(pedal) + 150.0
        best = gear
        for g in range(gear + 1, min(gear + 2, len(GEAR_RATIOS)) + 1):
            if speed_m_s * rpm_per_m_s[g - 1] >= floor:
                best = g
        return best
    lowest = 2  # gear 1 is only a launch gear (`launch_gear`)
    if rpm < downshift_rpm(pedal) and gear > lowest:
        target = downshift_rpm(pedal) + 250.0
        for g in range(gear - 1, max(gear - 2, lowest) - 1, -1):
            if speed_m_s * rpm_per_m_s[g - 1] >= target or g == max(gear - 2, lowest):
                return g
    return gear


def launch_gear(grade_rad: float) -> int:
    """Starting gear: 2 on the level, 1 on grades steeper than 2 %."""
    return 1 if grade_rad > 0.02 else 2
