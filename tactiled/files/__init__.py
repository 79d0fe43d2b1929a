"""Files on disk: recordings (.npz), bounded npz reading, the crash-safe journal, raw byte captures."""
