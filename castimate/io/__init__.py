"""Readers, unit conversion and the results file. No math beyond unit conversion lives here."""
