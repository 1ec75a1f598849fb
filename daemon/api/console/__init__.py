"""The operator console: a web page the daemon serves at ``/`` and the routes behind it (docs/console.md)."""
