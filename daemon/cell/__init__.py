"""The cell as the daemon holds it: its devices (:mod:`.devices`), the session every command that moves
hardware opens (:mod:`.session`), the supervisor (connections, health, safety latch, :mod:`.supervisor`),
motion as a capability (:mod:`.motion`), the tracker read at rest (:mod:`.tracker_reading`) and the
simulator's observer protocol (:mod:`.observer`). docs/architecture.md, "The cell layer".
"""
