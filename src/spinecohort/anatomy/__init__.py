"""The labeled reference thoracolumbar spine built from real bone surfaces, and what is measured on it."""
