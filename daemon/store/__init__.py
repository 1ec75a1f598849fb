"""The daemon's journal and files: the job store (:mod:`.job_store`, SQLite journal of jobs, steps and events; its
rows :mod:`.rows`, connections :mod:`.sqlite_db`, job folders :mod:`.job_folders`, crash recovery), the
live feed of its events (:mod:`.events`), the device events journaled (:mod:`.device_events`) and the
results by part (:mod:`.part_results`). docs/daemon.md, "Store".
"""
