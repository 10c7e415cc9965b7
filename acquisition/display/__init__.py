"""Display backends behind `acquisition.protocols.Display`."""
