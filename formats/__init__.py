"""File formats at the edge of relpoint: MCAP logs, PointCloud2/image codecs, trajectories, tables, PLY."""
