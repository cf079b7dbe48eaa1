"""Catalog schema (schema.sql) and an example STAC Item, shipped as archive.catalogs."""
