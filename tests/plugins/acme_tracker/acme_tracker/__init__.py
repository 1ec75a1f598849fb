"""The ACME tracker: a tandemscan tracker plugin (driver, settings and emulator)."""
