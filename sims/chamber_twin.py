"""Byte-level twin of a Sun Electronic Systems EC1x thermal-chamber controller.

It plays the instrument (no code shared with the driver) against the shared World, under `world.lock`:

* a command line is the command text + CR LF (delivered without the LF; a missing CR answers ?FRAMING).
* every command answers exactly one line ending CR LF: queries their value, settings/actions ``OK``,
  refusals ``?`` + reason: ?UNKNOWN COMMAND, ?BAD VALUE (not a number), ?RANGE (outside the controller's
  range), ?LIMIT (setpoint outside LTL/UTL), ?FRAMING.
* RATE=x (0 < x <= max_ramp_c_per_min, deg C/min), SET=x (LTL <= x <= UTL), ON, OFF, LTL=x, UTL=x (inside the
  hardware range, LTL < UTL), RATE?, SET?, LTL?, UTL?, C1? (air, world.chamber_air_c(), "%.2f"), STATUS?.
* power on: the world's chamber target is the SET= value at the RATE= ramp (world.set_chamber); power off: the
  world is driven to ambient (WorldParams.initial_temperature_c) through the same ramp and lag, and the stored
  SET= value waits for ON.
* SET? answers the controller's current (ramping) setpoint, world.chamber.controller_setpoint_c, while on. While
  the power is off (`set_query_while_off`, unconfirmed, so a choice): "held" answers the ramping setpoint as it
  was when the power went off (a controller that is off does not ramp: SET? stays where it was, whatever SET=
  arrives meanwhile; the public EC1x set documents SET? as the setpoint and nothing makes it move without
  power); "target" answers the last SET= value (a controller whose SET? echoes the stored target).
* power at start (`powered_at_start`): True, the controller is on and holding the world's initial temperature;
  False, the usual morning state: off, SET? held at the world's initial temperature, the STATUS? power and
  heat/cool flags N, until ON.
* silence at first contact (`silent_commands`): the first N command lines get no reply at all and are not
  executed (a controller still starting up; the public EC13 driver reads STATUS? several times at first
  contact "because sometimes the chamber needs a bit till it is responding").
* STATUS? layout (`status_layout`):
  - "flags16": 16 Y/N flags: 0 power, 1 heat enabled, 2 cool enabled, 8 ramping (on and
    the setpoint has not reached the target), the rest N;
  - "ec13": what the public Sun EC13 driver (achim1/skippylab, skippylab/instruments/climate_chambers.py)
    decodes: 18 Y/N flags then the self-test digit (`self_test`, 0 = ok), e.g. ``YNNNYYYNNNNNNNNNNN0``:
    0 power, 1 last command error (the previous command was refused), 4 heat enabled, 5 cool enabled, 6 valid
    set temperature (always Y), 8 ramping, 9 air below LTL, 10 air above UTL, the rest N.
* acknowledgements (`acknowledges_settings`): True answers every setting/action OK; False plays a
  controller that answers settings with nothing at all (as that public driver expects: it never reads one),
  refusals included: a refused setting then only shows in the read-back and in the last-command-error flag.
* `status_layout`, `self_test`, `acknowledges_settings`, `powered_at_start`, `set_query_while_off` and
  `silent_commands` have no default here: the station passes [sim] chamber_status_layout, chamber_self_test,
  chamber_acknowledges_settings, chamber_powered_at_start, chamber_set_query_while_off and
  chamber_silent_commands, whose defaults live in the configuration schema only.
* framing options (the real framing is unconfirmed): `command_end` (CR LF by default; CR or LF) and
  `reply_end` (CR LF by default; CR or LF).
"""

from __future__ import annotations

import math
import re

from sims.serial_twin import FaultableTwin
from sims.world import World

REPLY_END = b"\r\n"
STATUS_FLAGS = 16
STATUS_LAYOUTS = ("flags16", "ec13")
SET_QUERY_WHILE_OFF = ("held", "target")
EC13_FLAGS = 18
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)$")


class _Refused(Exception):
    pass


class ChamberTwin(FaultableTwin):
    """The EC1x controller. hardware_min_c/hardware_max_c: the controller's own range; max_ramp_c_per_min."""

    def __init__(
        self,
        world: World,
        *,
        hardware_min_c: float = -70.0,
        hardware_max_c: float = 180.0,
        max_ramp_c_per_min: float = 60.0,
        command_end: bytes = b"\r\n",
        reply_end: bytes = REPLY_END,
        status_layout: str,
        self_test: int,
        acknowledges_settings: bool,
        powered_at_start: bool,
        set_query_while_off: str,
        silent_commands: int,
    ) -> None:
        if command_end not in (b"\r", b"\n", b"\r\n") or reply_end not in (b"\r", b"\n", b"\r\n"):
            raise ValueError("command_end and reply_end must be CR, LF or CR LF")
        if status_layout not in STATUS_LAYOUTS:
            raise ValueError(f"status_layout must be one of {', '.join(STATUS_LAYOUTS)}, got {status_layout!r}")
        if not 0 <= self_test <= 9:
            raise ValueError(f"self_test must be one digit 0-9, got {self_test!r}")
        if set_query_while_off not in SET_QUERY_WHILE_OFF:
            raise ValueError(f"set_query_while_off must be held or target, got {set_query_while_off!r}")
        if int(silent_commands) < 0:
            raise ValueError(f"silent_commands must be >= 0, got {silent_commands!r}")
        self.set_query_while_off = set_query_while_off
        self.silent_commands = int(silent_commands)
        self.status_layout, self.self_test = status_layout, int(self_test)
        self.acknowledges_settings = bool(acknowledges_settings)
        self.last_command_error = False
        self.command_end, self.reply_end = command_end, reply_end
        self.world = world
        self.hardware_min_c = float(hardware_min_c)
        self.hardware_max_c = float(hardware_max_c)
        self.max_ramp_c_per_min = float(max_ramp_c_per_min)
        self.ltl_c, self.utl_c = self.hardware_min_c, self.hardware_max_c
        with world.lock:
            if not powered_at_start:
                world.chamber.heater_on = False
            self._power = world.chamber.heater_on
            self._target = world.chamber.target_c
            self._ramp = world.chamber.ramp_c_per_min
            self._held_setpoint = world.chamber.controller_setpoint_c  # SET? while off ("held")
        self.commands_seen = 0
        self._settings = {"SET": self._set, "RATE": self._rate, "LTL": self._ltl, "UTL": self._utl}
        self._queries = {
            "SET?": self._q_set,
            "RATE?": lambda: f"{self._ramp:.3f}",
            "LTL?": lambda: f"{self.ltl_c:.2f}",
            "UTL?": lambda: f"{self.utl_c:.2f}",
            "C1?": lambda: f"{self.world.chamber_air_c():.2f}",
            "STATUS?": self._status,
        }

    def execute(self, line: bytes) -> bytes:
        self.commands_seen += 1
        if self.commands_seen <= self.silent_commands:
            return b""  # still starting up: the line is neither answered nor executed
        query = False  # a query answers even when settings are not acknowledged
        try:
            body = self.command_body(line)
            if body is None:
                raise _Refused("FRAMING")
            try:
                text = body.decode("ascii")
            except UnicodeDecodeError:
                raise _Refused("UNKNOWN COMMAND") from None
            query = text.endswith("?")
            with self.world.lock:
                self.world.now()
                answer = self._dispatch(text)
        except _Refused as r:
            answer = f"?{r}"
        if not query:
            self.last_command_error = answer.startswith("?")
            if not self.acknowledges_settings:
                return b""
        return answer.encode("ascii") + self.reply_end

    def _dispatch(self, text: str) -> str:
        query = self._queries.get(text)
        if query is not None:
            return query()
        if text == "ON":
            self._power_on()
            return "OK"
        if text == "OFF":
            self._power_off()
            return "OK"
        name, eq, arg = text.partition("=")
        if eq and name in self._settings:
            if not _NUMBER.match(arg) or not math.isfinite(float(arg)):
                raise _Refused("BAD VALUE")
            self._settings[name](float(arg))
            return "OK"
        raise _Refused("UNKNOWN COMMAND")

    # ---------------------------------------------------------------- settings
    def _apply(self) -> None:
        if self._power:
            self.world.set_chamber(self._target, self._ramp)

    def _set(self, v: float) -> None:
        if not self.ltl_c <= v <= self.utl_c:
            raise _Refused("LIMIT")
        self._target = v
        self._apply()

    def _rate(self, v: float) -> None:
        if not 0.0 < v <= self.max_ramp_c_per_min:
            raise _Refused("RANGE")
        self._ramp = v
        self._apply()

    def _ltl(self, v: float) -> None:
        if not self.hardware_min_c <= v < self.utl_c:
            raise _Refused("RANGE")
        self.ltl_c = v

    def _utl(self, v: float) -> None:
        if not self.ltl_c < v <= self.hardware_max_c:
            raise _Refused("RANGE")
        self.utl_c = v

    def _power_on(self) -> None:
        self._power = True
        self.world.chamber.heater_on = True
        self._apply()

    def _power_off(self) -> None:
        if self._power:
            self._held_setpoint = self.world.chamber.controller_setpoint_c
        self._power = False
        self.world.chamber.heater_on = False
        self.world.set_chamber(self.world.params.initial_temperature_c, self._ramp)

    # ---------------------------------------------------------------- queries
    def _q_set(self) -> str:
        if self._power:
            return f"{self.world.chamber.controller_setpoint_c:.2f}"
        return f"{self._held_setpoint if self.set_query_while_off == 'held' else self._target:.2f}"

    def _status(self) -> str:
        ramping = self._power and self.world.chamber.controller_setpoint_c != self.world.chamber.target_c
        if self.status_layout == "flags16":
            flags = ["N"] * STATUS_FLAGS
            if self._power:
                flags[0] = flags[1] = flags[2] = "Y"
            flags[8] = "Y" if ramping else "N"
            return "".join(flags)
        flags = ["N"] * EC13_FLAGS
        air = self.world.chamber_air_c()
        for i, on in (
            (0, self._power),
            (1, self.last_command_error),
            (4, self._power),
            (5, self._power),
            (6, True),
            (8, ramping),
            (9, air < self.ltl_c),
            (10, air > self.utl_c),
        ):
            flags[i] = "Y" if on else "N"
        return "".join(flags) + str(self.self_test)
