-- Catalog index of an archive: <ARCHIVE>/catalog/index.sqlite (SQLite 3, standard library).
-- Rebuildable at any time from the STAC Items in <ARCHIVE>/catalog/items/ ('archive catalog rebuild').
-- Loaded by archive/catalog/index.py (tests check that the two copies agree).
-- Times are Unix epoch seconds (UTC, leap seconds already removed); bbox in degrees (WGS 84).

CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);

CREATE TABLE IF NOT EXISTS items (
    rowid          INTEGER PRIMARY KEY,   -- also the R*Tree id
    id             TEXT NOT NULL UNIQUE,  -- collection id = STAC Item id
    start_time     REAL NOT NULL,         -- epoch s, first line
    end_time       REAL NOT NULL,         -- epoch s, last line
    start_iso      TEXT NOT NULL,
    end_iso        TEXT NOT NULL,
    bands          INTEGER NOT NULL,
    min_wavelength REAL,                  -- nm; NULL when the flight has no wavelengths
    max_wavelength REAL,
    west           REAL NOT NULL,         -- exact bbox (the R*Tree holds it as float32, rounded outward)
    south          REAL NOT NULL,
    east           REAL NOT NULL,
    north          REAL NOT NULL,
    sensor         TEXT,
    gsd            REAL,                  -- m, nominal
    item_path      TEXT NOT NULL,         -- relative to the archive root
    geometry       BLOB                   -- footprint (lon/lat degrees) as WKB: exact spatial tests after the R*Tree
);

CREATE INDEX IF NOT EXISTS items_start ON items (start_time);
CREATE INDEX IF NOT EXISTS items_end ON items (end_time);
CREATE INDEX IF NOT EXISTS items_wavelength ON items (min_wavelength, max_wavelength);
CREATE INDEX IF NOT EXISTS items_wavelength_max ON items (max_wavelength);
CREATE INDEX IF NOT EXISTS items_gsd ON items (gsd);

CREATE VIRTUAL TABLE IF NOT EXISTS items_bbox USING rtree (
    id,
    west, east,     -- longitude range
    south, north    -- latitude range
);
