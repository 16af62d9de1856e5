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


def main():
    reg_json, dump, out = sys.argv[1:4]
    import json
    reg = json.load(open(reg_json))
    w, h = reg["width"], reg["height"]
    settings = [(2, 100, 2048)] if QUICK else [(1, 100, 2048), (2, 200, 2048), (3, 300, 4096)]
    results = []
    for res, iters, samples in settings:
        pdir = os.path.join(dump, f"elastix_r{res}_i{iters}")
        os.makedirs(pdir, exist_ok=True)
        pfile = os.path.join(pdir, "params.txt")
        open(pfile, "w").write(PARAMS.format(res=res, iters=iters, samples=samples))
        times, cpus, errors, mats = [], [], [], []
        for i, pair in enumerate(reg["pairs"]):
            odir = os.path.join(pdir, f"pair{i}")
            shutil.rmtree(odir, ignore_errors=True)
            os.makedirs(odir)
            cmd = ["elastix", "-f", os.path.join(dump, f"pair{i}_fixed.mhd"), "-m",
                   os.path.join(dump, f"pair{i}_moving.mhd"), "-p", pfile, "-out", odir,
                   "-threads", "1"]
            t, c = timed2(cmd, stdout=open(os.path.join(odir, "stdout.log"), "w"))
            times.append(t)
            cpus.append(c)
            m = read_transform(os.path.join(odir, "TransformParameters.0.txt"))
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
