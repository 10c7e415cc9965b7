"""Errors raised by acquisition code; each says which device or setting and what to do."""


class AcquisitionError(RuntimeError):
    """Base class for acquisition failures."""


class DeviceSettingsError(ValueError):
    """A device setting is out of range or not supported (message names the setting)."""


class DisplayError(AcquisitionError):
    """The display could not show an image."""


class CameraError(AcquisitionError):
    """The camera failed."""


class CameraTimeout(CameraError):
    """No frame arrived within the allowed time."""


class CameraDisconnected(CameraError):
    """The camera is gone (unplugged, powered off, link lost); reconnect may help."""

