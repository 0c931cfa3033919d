"""Finite-element export: Abaqus/CalculiX decks, the strict ccx wrapper, one model's deck/STL/VTU."""
