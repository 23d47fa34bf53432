"""Maps and their file formats: the occupancy grid (Nav2 ``map_server`` YAML + PGM), the
reflector map, a map built from scans and a trajectory. Imports core and robot only."""
