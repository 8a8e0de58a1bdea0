"""Loopback fakes: the device side of every protocol over real transports, and the simulated world.

Only tests, the benchmark and ``appliance.device_factory`` (when config says ``kind: loopback``)
import this package; production paths never do.
"""
