"""Paper 000 (MMPA / IPE): parking, IPE, path accuracy, ablations, scenes."""
