#!/usr/bin/env python3
"""A GIS pipeline with the irmosaic Python module: flight in, Cloud-Optimized GeoTIFF out.

Reads a flight written by `irmosaic synth` (frames.csv, frames/, pos.csv, camera.json), mosaics
it with irmosaic.Mosaicker, reads the mosaic window back as numpy arrays and hands them to GDAL's
Python API, which writes a COG (image band + alpha from the coverage).

  PYTHONPATH=build/python python3 samples/pipeline.py --flight FLIGHT_DIR --out mosaic.tif
  PYTHONPATH=build/python python3 samples/pipeline.py --cli build/cli/irmosaic --frames 24 \\
      --out mosaic.tif        # simulates the flight first (into a temporary folder)
"""
import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from osgeo import gdal

import irmosaic

gdal.UseExceptions()


def read_frames(flight_dir):
    """Yields (index, time_s, image) for the frames listed in frames.csv."""
    with open(os.path.join(flight_dir, "frames.csv")) as f:
        for row in csv.DictReader(f):
            ds = gdal.Open(os.path.join(flight_dir, row["file"]))
            yield int(row["index"]), float(row["time_s"]), ds.ReadAsArray()


def mosaic_flight(flight_dir, store_path):
    """Runs the pipeline over the flight; returns the finished Mosaicker."""
    options = irmosaic.MosaickerOptions(store_path, mode="overwrite")
    camera = irmosaic.CameraModel.load_json(os.path.join(flight_dir, "camera.json"))
    pos = irmosaic.PosTrack.load_csv(os.path.join(flight_dir, "pos.csv"))
    mosaicker = irmosaic.Mosaicker(options, camera, pos)
    for index, time_s, image in read_frames(flight_dir):
        result = mosaicker.push(index, time_s, image)
        if not result["placed"]:
            print(f"frame {index} skipped: {result['reason']}", file=sys.stderr)
    mosaicker.finish()
    return mosaicker


def write_cog(mosaicker, out_path):
    """Writes the whole mosaic as a COG; returns (width, height, covered fraction)."""
    col, row, width, height = mosaicker.bounds()
    image, coverage, geotransform, crs_wkt = mosaicker.read_window(col, row, width, height)
    gdal_type = {np.dtype(np.uint8): gdal.GDT_Byte, np.dtype(np.uint16): gdal.GDT_UInt16,
                 np.dtype(np.float32): gdal.GDT_Float32}[image.dtype]
    mem = gdal.GetDriverByName("MEM").Create("", width, height, 2, gdal_type)
    mem.SetGeoTransform(geotransform)
    mem.SetProjection(crs_wkt)
    mem.GetRasterBand(1).WriteArray(image)
    alpha = mem.GetRasterBand(2)
    alpha.SetColorInterpretation(gdal.GCI_AlphaBand)
    # The alpha band spans the image type's range: full scale where painted.
    full = {gdal.GDT_Byte: 255, gdal.GDT_UInt16: 65535, gdal.GDT_Float32: 1.0}[gdal_type]
    alpha.WriteArray(np.where(coverage > 0, full, 0).astype(image.dtype))
    gdal.GetDriverByName("COG").CreateCopy(out_path, mem,
                                           options=["COMPRESS=ZSTD", "PREDICTOR=YES"])
    return width, height, float((coverage > 0).mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flight", help="flight folder written by `irmosaic synth`")
    parser.add_argument("--cli", help="irmosaic CLI, to simulate a flight when --flight is absent")
    parser.add_argument("--frames", type=int, default=24, help="frames to simulate")
    parser.add_argument("--out", required=True, help="output COG path")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as work:
        flight = args.flight
        if flight is None:
            if args.cli is None:
                parser.error("give --flight, or --cli to simulate one")
            flight = os.path.join(work, "flight")
            config = os.path.join(work, "synth.json")
            with open(config, "w") as f:  # Fractal terrain around this origin.
                f.write('{"origin_lat_deg": 47.2, "origin_lon_deg": 8.5}')
            subprocess.run([args.cli, "synth", "--config", config, "--out", flight,
                            "--frames", str(args.frames)],
                           check=True, stderr=subprocess.DEVNULL)
        start = time.monotonic()
        mosaicker = mosaic_flight(flight, os.path.join(work, "mosaic.irmosaic"))
        summary = mosaicker.summary()
        width, height, covered = write_cog(mosaicker, args.out)
        seconds = time.monotonic() - start

    # Check what was written: a georeferenced COG GDAL reads back with the mosaic's size.
    ds = gdal.Open(args.out)
    layout = ds.GetMetadataItem("LAYOUT", "IMAGE_STRUCTURE")
    ok = (ds.RasterXSize, ds.RasterYSize) == (width, height) and layout == "COG" and \
        ds.GetSpatialRef() is not None and summary["frames_placed"] > 0
    print(f"{summary['frames_placed']}/{summary['frames_pushed']} frames placed "
          f"({summary['frames_registered']} registered), gsd {summary['gsd_m']:.3f} m, "
          f"{width}x{height} px ({covered:.0%} covered) -> {args.out} [{layout}] "
          f"in {seconds:.1f} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
