"""Block-tower datasets: towers, materials, voxels, renders, shards on disk, the card."""
