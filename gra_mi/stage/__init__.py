"""The lightstage (paper Sec. 3 and Supp. "Details about the Dataset"): calibration (LEDs, cameras), environment maps
and their mapping onto the LEDs, procedural envmaps, and Mitsuba scene files with the loader that changes frame
and lighting in place."""
