"""USB: pyusb discovery of UVC and USB3 Vision cameras, and the optional flip trigger box."""
