"""What every layer shares: the file formats and the job plumbing they are written with.

`plan` (the pattern plan), `maps` and `maps_file` (decoded maps, and the laid-out file the
decoder writes into; `npz_store` lays out its NPZ members), `frame_store` (a pose's raw
frames), `observations` (a passive target's sparse correspondences, one view per file),
`atomic` (the one atomic file writer), `progress` (progress, cancel and the task context).
`acquisition`, `api` and `hw_mocks` import these modules directly; the numerics come through
the front door, `calibration` itself. The formats are described in docs/formats.md.
"""
