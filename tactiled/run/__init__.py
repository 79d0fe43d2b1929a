"""Running the chain on a stream: the ingest core (bytes -> frames -> pipeline) and replay of recordings."""
