"""feature_extractor: drainage-pattern minutiae of camera and landmark images (dissertation ch. 3).

Subscribes to the ground-projected camera frames (``/camera/image_ground``) and the rendered
landmarks (``/landmark/image``, latched), both ``terrain_nav_msgs/GeoImage``; publishes their
minutiae as ``MinutiaArray`` on ``/camera/minutiae`` and ``/landmark/minutiae`` (latched), with
the source georeference and (``attach_creases``, ``attach_ridges``) the crease and ridge
skeletons for the matcher's crease and ridge checks, and the crease images on
``/camera/creases`` and ``/landmark/creases`` for debugging.
A camera frame that is mostly cloud (:mod:`~.core.features.clouds`, ``cloud.*``: bright and
featureless) is answered with an empty array and that reason.
An image with no drainage (flat, lake, cloud) yields an empty array whose ``reason`` says so,
and so does every camera frame that has no minutiae for another reason (not projected,
unusable, extraction failed): the matcher answers each frame.

Parameters are the fields of :class:`~.core.features.creases.CreaseParams` (``crease.*``, Table 3.1)
and :class:`~.core.features.minutiae.MinutiaParams` (``minutia.*``); a change is validated by those
classes and refused with their message when invalid. ``lighting: compensated`` extracts the
creases from the terrain curvature estimated with the sun each image carries
(:func:`~.core.features.hillshade.shading_curvature`) instead of from the shading itself, so camera
frames and landmarks lit from different directions still agree; an image without a known sun
is then used as it is, with a warning.
"""

from __future__ import annotations

import math
import time
from collections import Counter

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import Image

from terrain_nav_msgs.msg import GeoImage, MinutiaArray

from ..core.features.clouds import CloudParams, cloud_cover
from ..core.features.creases import CreaseParams
from ..core.features.hillshade import check_lighting, extractor_input
from ..core.features.minutiae import FeatureExtractor, MinutiaParams, warm_up
from ..core.matching.pva_fix import reason_kind
from . import conversions as cv
from .ros_common import (
    DIAG_ERROR,
    DIAG_OK,
    LATCHED_QOS,
    RELIABLE_QOS,
    check_parameters_known,
    contained,
    declare,
    declare_settings,
    new_failures,
    publish_diagnostics,
    run,
    settings_from_parameters,
)


class FeatureExtractorNode(Node):
    """Creases and minutiae for both image streams, with one set of settings."""

    def __init__(self):
        super().__init__("feature_extractor")
        declare_settings(self, "crease", CreaseParams())
        declare_settings(self, "minutia", MinutiaParams())
        declare_settings(self, "cloud", CloudParams())
        self.publish_creases = declare(self, "publish_creases", True,
                                       "publish the crease images on the debug topics")
        self.attach_creases = declare(self, "attach_creases", True,
                                      "send the crease skeleton with the minutiae (the "
                                      "matcher's crease check)")
        self.attach_ridges = declare(self, "attach_ridges", True,
                                     "send the ridge skeleton with the minutiae (the "
                                     "matcher's ridge check of sets with few minutiae; "
                                     "match.threshold is calibrated with it)")
        self.lighting = declare(self, "lighting", "shading",
                                "extractor input: 'shading' (the image) or 'compensated' "
                                "(terrain curvature from the shading and the image's sun)")
        check_lighting(self.lighting)
        diagnostics_period = declare(self, "diagnostics_period", 1.0,
                                     "period of /feature_extractor/diagnostics, wall clock [s]",
                                     min_value=0.01)
        check_parameters_known(self)  # before the extractor is built and its kernels loaded
        self.images = Counter()               # per stream
        self.without_minutiae = Counter()     # per stream and reason kind
        self.extract_ms = {"camera": [], "landmark": []}   # since the last report
        self.extractor = self._build()
        self.cloud_params = settings_from_parameters(self, "cloud", CloudParams())
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.outputs = {}
        for name, source, qos in (("camera", MinutiaArray.SOURCE_CAMERA, RELIABLE_QOS),
                                  ("landmark", MinutiaArray.SOURCE_LANDMARK, LATCHED_QOS)):
            self.outputs[name] = (
                self.create_publisher(MinutiaArray, f"{name}/minutiae", qos),
                self.create_publisher(Image, f"{name}/creases", qos), source)
        # numba's kernels load on first use (seconds; compiled, tens of seconds): not on the
        # first frame's clock, and before subscribing (a replay waits for the subscribers)
        warm_up()
        self.create_subscription(GeoImage, "camera/image_ground",
                                 lambda m: self.on_image(m, "camera"), RELIABLE_QOS)
        self.create_subscription(GeoImage, "landmark/image",
                                 lambda m: self.on_image(m, "landmark"), LATCHED_QOS)
        publish_diagnostics(self, "feature_extractor/diagnostics", diagnostics_period,
                            self.diagnostics)

    def _build(self, overrides=None, ridges=None) -> FeatureExtractor:
        return FeatureExtractor(
            settings_from_parameters(self, "crease", CreaseParams(), overrides),
            settings_from_parameters(self, "minutia", MinutiaParams(), overrides),
            ridges=self.attach_ridges if ridges is None else ridges)

    def on_set_parameters(self, params) -> SetParametersResult:
        """Validate a change with the core's own checks before accepting it; every setting
        applies from the next image."""
        new = {p.name: p.value for p in params}
        ridges = bool(new.get("attach_ridges", self.attach_ridges))
        lighting = new.get("lighting", self.lighting)
        try:
            check_lighting(lighting)
            self.extractor = self._build(params, ridges)
            cloud_params = settings_from_parameters(self, "cloud", CloudParams(), params)
        except (ValueError, TypeError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        self.attach_ridges = ridges
        self.attach_creases = bool(new.get("attach_creases", self.attach_creases))
        self.publish_creases = bool(new.get("publish_creases", self.publish_creases))
        self.lighting = lighting
        self.cloud_params = cloud_params
        return SetParametersResult(successful=True)

    @contained
    def on_image(self, msg: GeoImage, stream: str) -> None:
        self.images[stream] += 1
        start = time.monotonic()
        try:
            self._extract(msg, stream)
            self.extract_ms[stream].append(1e3 * (time.monotonic() - start))
        except Exception as err:
            self._no_minutiae(msg, stream,
                              f"feature extraction failed: {type(err).__name__}: {err}")
            raise   # logged and counted by @contained

    def _no_minutiae(self, msg: GeoImage, stream: str, reason: str, log: bool = True) -> None:
        """A camera frame without minutiae still gets its (empty) set, so that the matcher
        answers it; a landmark image without them is only logged (there is no frame to
        answer, and an empty set would displace the region's last good one)."""
        self.without_minutiae[f"{stream}: {reason_kind(reason)}"] += 1
        if stream == "camera":
            minutiae_pub, _, source = self.outputs[stream]
            minutiae_pub.publish(cv.empty_minutiae_msg(msg.header, source, reason))
        if log:
            self.get_logger().error(f"{stream} image without minutiae: {reason}",
                                    throttle_duration_sec=2.0)

    def _extract(self, msg: GeoImage, stream: str) -> None:
        if msg.reason:   # not projected: the camera ingest has said why
            self._no_minutiae(msg, stream, msg.reason, log=False)
            return
        try:
            image, georef, valid = cv.msg_to_geo_image(msg)
        except cv.ConversionError as err:
            self._no_minutiae(msg, stream, f"unusable {stream} image: {err}")
            return
        if stream == "camera":   # a render has no cloud
            cover = cloud_cover(image, valid, self.cloud_params)
            if cover.reason:
                self._no_minutiae(msg, stream, cover.reason, log=False)
                return
        features = self.extractor(self.lighting_normalised(image, valid, msg, stream),
                                  georef, valid)
        minutiae_pub, crease_pub, source = self.outputs[stream]
        origin = cv.enu_origin_of(msg.georef)
        creases = features.creases.skeleton() if self.attach_creases else None
        out = cv.minutiae_to_msg(features.minutiae, msg.header, source, origin,
                                 msg.georef.source_crs, creases=creases,
                                 ridges=features.ridges)
        cv.copy_projection(msg, out)
        minutiae_pub.publish(out)
        if self.publish_creases:
            crease_pub.publish(cv.array_to_image(features.crease_image(), "mono8", msg.header))
        if features.minutiae.reason:
            self.without_minutiae[f"{stream}: {reason_kind(features.minutiae.reason)}"] += 1
            self.get_logger().info(f"{stream}: no minutiae ({features.minutiae.reason})",
                                   throttle_duration_sec=5.0)

    def lighting_normalised(self, image, valid, msg: GeoImage, stream: str):
        """The image the extractor sees under the ``lighting`` setting."""
        sun = cv.geo_image_sun(msg)
        if self.lighting == "compensated" and sun is None:
            self.get_logger().warning(f"{stream} image carries no sun: shading used as is",
                                      throttle_duration_sec=10.0)
            return image
        return extractor_input(image, self.lighting, sun, valid)

    def diagnostics(self) -> list:
        """Images per stream and those without minutiae (by reason) so far, the extraction
        time since the last report; an error when extraction failed since then."""
        failures, new = new_failures(self)
        level, message = DIAG_OK, "ok"
        if new:
            level, message = DIAG_ERROR, f"{new} image(s) failed: see the log"
        values = {"failures": failures}
        for stream, times in self.extract_ms.items():
            values[f"{stream}_images"] = self.images[stream]
            values[f"{stream}_ms_median"] = float(np.median(times)) if times else math.nan
            times.clear()
        values.update({f"no minutiae: {k}": n for k, n in self.without_minutiae.most_common()})
        return [cv.diagnostic_status("feature_extractor", level, message, values,
                                     "terrain_nav")]


def main(args=None):
    return run(FeatureExtractorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
