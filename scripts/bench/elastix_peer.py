#!/usr/bin/python3
"""elastix (rigid EulerTransform 2-D, one thread) on the slice pairs register_bench dumped, at a
few pyramid/iteration settings; errors against the phantom's truth, measured as for vispack.
Usage: elastix_peer.py REGISTER_JSON DUMP_DIR OUT_JSON"""
import os
import re
import shutil
import sys

import numpy as np

from common import QUICK, median, pair_error_px, rms, timed2, write_json

PARAMS = """(FixedInternalImagePixelType "float")
(MovingInternalImagePixelType "float")
(FixedImageDimension 2)
(MovingImageDimension 2)
(Registration "MultiResolutionRegistration")
(Interpolator "BSplineInterpolator")
(ResampleInterpolator "FinalBSplineInterpolator")
(Resampler "DefaultResampler")
(FixedImagePyramid "FixedSmoothingImagePyramid")
(MovingImagePyramid "MovingSmoothingImagePyramid")
(Optimizer "AdaptiveStochasticGradientDescent")
(Transform "EulerTransform")
(Metric "AdvancedNormalizedCorrelation")
(AutomaticScalesEstimation "true")
(AutomaticTransformInitialization "false")
(HowToCombineTransforms "Compose")
(NumberOfResolutions {res})
(MaximumNumberOfIterations {iters})
(NumberOfSpatialSamples {samples})
(NewSamplesEveryIteration "true")
(ImageSampler "RandomCoordinate")
(BSplineInterpolationOrder 1)
(FinalBSplineInterpolationOrder 1)
(DefaultPixelValue 0)
(WriteResultImage "false")
(ResultImagePixelType "float")
"""


def read_transform(path):
    text = open(path).read()
    p = [float(v) for v in re.search(r"\(TransformParameters ([^)]*)\)", text).group(1).split()]
    c = [float(v) for v in re.search(r"\(CenterOfRotationPoint ([^)]*)\)", text).group(1).split()]
    theta, tx, ty = p
    r = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    cc = np.array(c)
    # elastix maps fixed points to moving points: T(x) = R (x - c) + c + t.
    off = cc - r @ cc + np.array([tx, ty])
    return np.hstack([r, off[:, None]])


def settings():
    """(resolutions, iterations, samples) from cheap to accurate."""
    return [(2, 100, 2048)] if QUICK else [(1, 50, 1024), (1, 100, 2048), (2, 200, 2048), (3, 300, 4096)]


def write_params(dump, res, iters, samples):
    pdir = os.path.join(dump, f"elastix_r{res}_i{iters}")
    os.makedirs(pdir, exist_ok=True)
    pfile = os.path.join(pdir, "params.txt")
    open(pfile, "w").write(PARAMS.format(res=res, iters=iters, samples=samples))
    return pdir, pfile


def run_pair(pfile, fixed, moving, odir):
    """One elastix run: (wall s, CPU s, 2x3 fixed-to-moving matrix). The time includes the
    process start, reading both files and writing the result files."""
    shutil.rmtree(odir, ignore_errors=True)
    os.makedirs(odir)
    cmd = ["elastix", "-f", fixed, "-m", moving, "-p", pfile, "-out", odir, "-threads", "1"]
    t, c = timed2(cmd, stdout=open(os.path.join(odir, "stdout.log"), "w"))
    return t, c, read_transform(os.path.join(odir, "TransformParameters.0.txt"))


def fixed_cost(dump, reps=5):
    """elastix's fixed cost per run: process start, component registration, parameter parsing,
    writing its result files: the same command on a 16x16 pair, one resolution, one iteration.
    Returns (wall s, CPU s), medians of `reps`."""
    d = os.path.join(dump, "elastix_fixed_cost")
    os.makedirs(d, exist_ok=True)
    img = (np.add.outer(np.arange(16), np.arange(16)) * 7 % 256).astype(np.uint8)
    for name in ("fixed", "moving"):
        img.tofile(os.path.join(d, name + ".raw"))
        open(os.path.join(d, name + ".mhd"), "w").write(
            "ObjectType = Image\nNDims = 2\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
            "ElementSpacing = 1 1\nOffset = 0 0\nDimSize = 16 16\nElementType = MET_UCHAR\n"
            f"ElementDataFile = {name}.raw\n")
    _, pfile = write_params(d, 1, 1, 64)
    tc = [run_pair(pfile, os.path.join(d, "fixed.mhd"), os.path.join(d, "moving.mhd"),
                   os.path.join(d, "out"))[:2] for _ in range(reps)]
    return median([t for t, _ in tc]), median([c for _, c in tc])


def main():
    reg_json, dump, out = sys.argv[1:4]
    import json
    reg = json.load(open(reg_json))
    w, h = reg["width"], reg["height"]
    results = []
    for res, iters, samples in settings():
        pdir, pfile = write_params(dump, res, iters, samples)
        times, cpus, errors, mats = [], [], [], []
        for i, pair in enumerate(reg["pairs"]):
            t, c, m = run_pair(pfile, os.path.join(dump, f"pair{i}_fixed.mhd"),
                               os.path.join(dump, f"pair{i}_moving.mhd"), os.path.join(pdir, f"pair{i}"))
            times.append(t)
            cpus.append(c)
            mats.append(m.tolist())
            errors.append(pair_error_px(m, pair["truth"], w, h))
        results.append({"resolutions": res, "iterations": iters, "samples": samples,
                        "seconds_per_pair": median(times), "cpu_seconds_per_pair": median(cpus),
                        "times": times, "errors_px": errors,
                        "rms_px": rms(errors), "estimates": mats})
        print(f"elastix r{res} i{iters}: {1e3 * median(times):.0f} ms/pair, RMS {rms(errors):.3f} px",
              file=sys.stderr)
    write_json(out, {"width": w, "height": h, "threads": 1, "results": results})


if __name__ == "__main__":
    main()
