"""Genuine SocketCAN for tests on hosts without it: a User-Mode Linux guest with ``vcan0``.

Test infrastructure only (stdlib; no rclpy, no python-can): :mod:`.runner` boots
the guest and runs a job in it, :mod:`.fpu` works around the guest kernel's
FPU-state limits on modern x86 hosts. See docs/socketcan.md.
"""
