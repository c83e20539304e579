"""Many runs at once: batches of tracks as one vmapped, sharded computation, and resumable studies
(grids of cells with records and a table)."""
