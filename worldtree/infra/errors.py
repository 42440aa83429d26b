"""The one exception type that command-line tools turn into a one-line message, and its kind about one
setting's value."""

from __future__ import annotations


class UserError(Exception):
    """Bad input or configuration the user can fix.

    The message must name the file or option at fault and the fix, on one line. The CLIs print it as
    ``error: <message>`` and exit with status 2, without a traceback.
    """


class SettingError(UserError):
    """A :class:`UserError` about one setting's value, named as the library knows it: ``setting`` is a config
    field as ``Class.field`` (``WorldTreeConfig.depth``) or a parameter (``device``). The message reads
    ``<setting> <value>: <why>``; a command line that took the setting from an option of its own names that
    option instead (:meth:`as_option`), so the library never names a flag."""

    def __init__(self, setting: str, value: object, why: str) -> None:
        super().__init__(f"{setting} {value}: {why}")
        self.setting, self.value, self.why = setting, value, why

    @classmethod
    def of_field(cls, obj: object, name: str, why: str, shown: object = None) -> SettingError:
        """About field ``name`` of the config ``obj`` (``Class.name``); its value shown as ``shown``, or as
        it is."""
        return cls(f"{type(obj).__name__}.{name}", getattr(obj, name) if shown is None else shown, why)

    def __reduce__(self):  # pickled across processes (sweep executors) with its fields
        return type(self), (self.setting, self.value, self.why)

    def as_option(self, option: str) -> UserError:
        """The same error as given on a command line: ``<option> <value>: <why>``."""
        return UserError(f"{option} {self.value}: {self.why}")
