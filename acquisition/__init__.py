"""Everything that touches hardware or time: pattern plans, displays, cameras, the controller."""
