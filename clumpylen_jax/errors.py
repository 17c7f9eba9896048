"""The one exception type for invalid user input.

Every check that rejects a setting raises `ConfigError` with the setting's name,
the value received and what was expected, before any computation starts. The
CLI turns it into one line on stderr and exit status 2.
"""


class ConfigError(ValueError):
    """Invalid user input: names the setting, the value and what was expected."""

    def __init__(self, setting: str, value, expected: str):
        self.setting = setting
        self.value = value
        self.expected = expected
        super().__init__(f"{setting} = {value!r}: expected {expected}")


def require(condition: bool, setting: str, value, expected: str) -> None:
    """Raise ConfigError(setting, value, expected) unless `condition` holds."""
    if not condition:
        raise ConfigError(setting, value, expected)
