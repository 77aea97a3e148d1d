"""Vehicle traces: SUMO runs (through libsumo, one subprocess each) recorded once into
cached, checksummed tensors per split (train, eval, test)."""
