"""The photo stage: metadata (EXIF/XMP), heights above the ground, footprints and GSD."""
