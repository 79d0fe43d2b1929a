"""The daemon and what it serves: publisher, raw-sample batches, the recording sink, MCAP export."""
