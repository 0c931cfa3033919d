"""Stage 3 — the hexahedral FE mesh: template, BCPD registration and morphing, hex SSM, disc contact, quality and repair."""
