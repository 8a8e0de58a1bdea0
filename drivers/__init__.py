"""Device drivers and transports: serial/pty/TCP, pyusb, V4L2 and files.

``drivers.loopback`` holds the device side of every protocol and the simulated world; production
code never imports it (checked by import-linter, see pyproject.toml).
"""
