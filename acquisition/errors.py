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


class FrameLost(CameraError):
    """A triggered frame came back incomplete (packets lost on the link, not recovered by
    resend): no frame will come for that trigger, so trigger again instead of waiting."""
