"""Test machinery (not installed with redarm_ros): the UML SocketCAN guest runner and its scenario
script, CAN bus fakes and leak tracking. Tests import it as ``support`` (pytest puts test/ on the path)."""
