"""Supervisor, job runner, store, REST API and CLI."""
