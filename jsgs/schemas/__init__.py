"""The JSON Schemas of every file jsgs and jsgstools write or read (``*.schema.json`` beside this module,
shipped as package data). Loading and validation live in :mod:`jsgs.base.schema`."""
