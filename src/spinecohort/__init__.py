"""spinecohort: thoracolumbar spine SSM and virtual cohort of hexahedral FE models.

Units are millimetres and degrees throughout.
"""

__version__ = "0.1.0"
