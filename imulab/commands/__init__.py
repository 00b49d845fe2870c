"""One module per ``imulab`` sub-command; each exposes a click command named ``command``."""
