"""Readers and writers of the formats users bring and take away (see docs/formats.md)."""
