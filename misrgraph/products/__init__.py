"""The calibration's products on MISR's SOM grid: Projection Parameters (:mod:`.pp`)."""
