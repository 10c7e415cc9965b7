"""Camera backends behind `acquisition.protocols.Camera`."""
