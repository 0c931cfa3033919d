"""FE validation: segmental range of motion in CalculiX against in-vitro data."""
