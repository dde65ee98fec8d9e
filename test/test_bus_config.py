"""The device config file's keys (core/machine/bus.py ``load_bus_config``): a key the
bridge does not read is refused in one line naming it and a close match; and the
bridge's silence limit, a time counted in SYNCs."""
from __future__ import annotations

import pytest

from stewart63_ros.core.machine.bus import BusConfigError, default_bus_config_path, load_bus_config

CONFIG = default_bus_config_path()
EDS = CONFIG.with_name('stewart63_drive.eds')


@pytest.mark.parametrize('edit, words', [
    # ran with the default 100 ms heartbeat, silently
    (('heartbeat_ms: 100', 'hearbeat_ms: 20'), "unknown key 'hearbeat_ms': did you mean "
                                                'heartbeat_ms?'),
    # was "lead_m is missing"
    (('lead_m: 0.005, gear_ratio: 5.0', 'lead_mm: 0.005, gear_ratio: 5.0'),
     "legs[0] (leg_1): unknown key 'lead_mm': did you mean lead_m?"),
    (('bitrate: 1000000}', 'bitrate: 1000000, bitrte: 5}'),
     "buses[0]: unknown key 'bitrte': did you mean bitrate?"),
    (('heartbeat_ms: 100', 'heartbeat_ms: 100\nwatchdog: 3'), "unknown key 'watchdog' (known:"),
])
def test_an_unknown_key_is_refused_naming_it_and_a_close_match(tmp_path, edit, words):
    text = CONFIG.read_text()
    assert edit[0] in text
    (tmp_path / 'stewart63_drive.eds').write_text(EDS.read_text())
    path = tmp_path / 'canopen.yaml'
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(BusConfigError) as caught:
        load_bus_config(path)
    message = str(caught.value)
    assert words in message and '\n' not in message and 'missing' not in message, message


def test_the_packaged_config_has_no_unknown_key():
    assert len(load_bus_config(CONFIG).legs) == 6


def test_a_drive_is_silent_after_the_same_time_at_any_rate_counted_in_syncs():
    from stewart63_ros.canbus.sync import silent_cycles
    # the bridge's tpdo_missing_error_ms (20 ms): the SYNCs covering it
    assert silent_cycles(20.0, 200.0) == 4
    assert silent_cycles(20.0, 1000.0) == 20
    assert silent_cycles(25.0, 200.0) == 5          # what 5 cycles at 200 Hz were
    assert silent_cycles(20.5, 1000.0) == 21        # a part of a period is one more
    assert silent_cycles(0.1, 200.0) == 1           # never none
