"""Protocol emulators: servers that answer as the real devices do, for hardware-in-the-loop tests."""
