"""The rig daemon ``excavator-rtd``: config, sd_notify, job store, control socket, signals."""
