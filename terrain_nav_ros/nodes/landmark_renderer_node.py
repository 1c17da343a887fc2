"""landmark_renderer: render each DEM tile into a georeferenced landmark image (dissertation 2.2).

Subscribes to the latched ``/metamap/tile``; for every new tile it uploads the heights to the
GPU renderer (moderngl, headless EGL: Mesa llvmpipe on a CPU-only computer) and publishes the
orthographic nadir render as a north-up ``terrain_nav_msgs/GeoImage`` on ``/landmark/image``
(latched too), on the tile's own grid or at another GSD. The sun is fixed or follows the
tile's stamp (date, time and place: the light the camera saw); with the stamp policy the
landmark is rendered again once the sun has moved ``max_sun_change`` degrees since (shaded
creases move with the sun: minutiae repeat >= 70 % only within ~2 degrees of sun azimuth).
The GL context is created once.
"""

from __future__ import annotations

import numpy as np
from rclpy.node import Node

from terrain_nav_msgs.msg import DemTile, GeoImage
from terrain_nav_msgs.srv import RenderView

from ..core.render.renderer import (
    AlbedoRamp,
    LandmarkRenderer,
    PinholeCamera,
    RendererError,
    create_headless_context,
    display_u8,
)
from ..core.render.sun import sun_at, sun_separation
from ..core.terrain.georef import GeoReference
from . import conversions as cv
from .ros_common import (
    LATCHED_QOS,
    check_parameters_known,
    contained,
    declare,
    reject_all_changes,
    run,
)


class LandmarkRendererNode(Node):
    """Nadir landmark images of the metamap's tiles."""

    def __init__(self):
        super().__init__("landmark_renderer")
        self.gsd = declare(self, "gsd", 0.0, "landmark GSD [m/px]; 0 = the tile's", min_value=0.0)
        self.sun_policy = declare(self, "sun_policy", "fixed",
                                  "fixed: sun_azimuth/sun_elevation; stamp: solar position at "
                                  "the tile's stamp and the ENU origin")
        self.sun = (declare(self, "sun_azimuth", 315.0, "sun azimuth, clockwise from north "
                            "[deg]", min_value=0.0, max_value=360.0),
                    declare(self, "sun_elevation", 45.0, "sun elevation [deg]",
                            min_value=1.0, max_value=90.0))
        self.shadows = declare(self, "shadows", True,
                               "cast shadows, as a camera sees them (a second ray per pixel)")
        albedo = AlbedoRamp(
            tree_line=declare(self, "tree_line", 2400.0, "vegetation -> rock elevation [m]"),
            snow_line=declare(self, "snow_line", 3400.0, "rock -> snow elevation [m]"))
        max_steps = declare(self, "max_steps", 256, "sphere-tracing step budget per ray",
                            min_value=8, max_value=4096)
        self.max_sun_change = declare(self, "max_sun_change", 2.0,
                                      "stamp policy: render the landmark again when the sun "
                                      "has moved this far since [deg]; 0 = never",
                                      min_value=0.0)
        sun_check_period = declare(self, "sun_check_period", 10.0,
                                   "how often the sun's motion is checked [s]", min_value=0.01)
        self.max_size = declare(self, "max_image_size", 4096,
                                "largest side of a tile or view rendered [px] (4096: ~15 s and "
                                "2 GB on llvmpipe)", min_value=16, max_value=16384)
        if self.sun_policy not in ("fixed", "stamp"):
            raise ValueError(f"sun_policy must be 'fixed' or 'stamp', not {self.sun_policy!r}")
        check_parameters_known(self)  # before the OpenGL context is made
        self.add_on_set_parameters_callback(reject_all_changes)
        self.renderer = LandmarkRenderer(create_headless_context(), max_steps=max_steps,
                                         albedo=albedo, shadows=self.shadows)
        info = self.renderer.ctx.info
        self.get_logger().info(f"OpenGL: {info['GL_RENDERER']} ({info['GL_VERSION']})")
        self.pub = self.create_publisher(GeoImage, "landmark/image", LATCHED_QOS)
        self.create_subscription(DemTile, "metamap/tile", self.on_tile, LATCHED_QOS)
        self.create_service(RenderView, "landmark_renderer/render_view", self.on_render_view)
        self.rendered = 0
        self.last_tile_msg: DemTile | None = None
        self.rendered_sun = None   # the sun of the latest landmark
        if self.sun_policy == "stamp" and self.max_sun_change > 0:
            self.create_timer(sun_check_period, self.check_sun)

    def sun_for(self, msg: DemTile, stamp_s: float | None = None):
        """(azimuth, elevation) for a tile under the configured policy, at the tile's stamp
        or at ``stamp_s``."""
        if self.sun_policy == "fixed":
            return self.sun
        if stamp_s is None:
            stamp_s = cv.stamp_to_sec(msg.header.stamp)
        az, el = sun_at(stamp_s, msg.georef.enu_origin_latitude,
                        msg.georef.enu_origin_longitude)
        if el < 5.0:
            self.get_logger().warning(f"sun only {float(el):.1f} deg high at the tile's stamp; "
                                      f"using {self.sun}", throttle_duration_sec=60.0)
            return self.sun
        return az, el

    @contained
    def on_tile(self, msg: DemTile) -> None:
        try:
            heights, georef = cv.msg_to_dem_tile(msg)
        except cv.ConversionError as err:
            self.get_logger().error(f"bad DemTile: {err}")
            return
        void = ~np.isfinite(heights)
        if void.all():
            self.get_logger().warning("DemTile has no valid elevation; no landmark")
            return
        filled = np.where(void, np.nanmin(heights), heights)
        out = georef if self.gsd <= 0 else GeoReference.centred(
            *georef.centre, self.gsd, round(georef.width * georef.gsd / self.gsd),
            round(georef.height * georef.gsd / self.gsd))
        if max(georef.width, georef.height, out.width, out.height) > self.max_size:
            self.get_logger().error(
                f"DemTile of {georef.width}x{georef.height} px (landmark {out.width}x"
                f"{out.height}): at most {self.max_size} px a side (max_image_size); "
                "no landmark")
            return
        try:
            self.renderer.set_terrain(filled, georef)
            self.last_tile_msg = msg
            sun = self.sun_for(msg)
            result = self.renderer.render_nadir(out, sun=sun)
        except (RendererError, ValueError) as err:
            self.get_logger().error(f"cannot render tile: {err}")
            return
        valid = result.mask
        if void.any():  # landmark pixels over DEM voids carry no information
            col, row = georef.enu_to_pixel(*out.pixel_to_enu(
                np.arange(out.width)[None, :], np.arange(out.height)[:, None]))
            r = np.clip(np.rint(row).astype(int), 0, georef.height - 1)
            c = np.clip(np.rint(col).astype(int), 0, georef.width - 1)
            valid &= ~void[r, c]
        image = display_u8(result.grey)
        self.pub.publish(cv.geo_image_to_msg(
            image, out, msg.header, valid, cv.enu_origin_of(msg.georef), msg.georef.source_crs,
            sun))
        self.rendered += 1
        self.rendered_sun = sun
        self.get_logger().info(f"landmark {out.width}x{out.height} px at {out.gsd:g} m/px "
                               f"centred ({out.centre[0]:.0f}, {out.centre[1]:.0f}) m, sun "
                               f"{float(sun[0]):.1f}/{float(sun[1]):.1f} deg")

    @contained
    def check_sun(self) -> None:
        """Render the current tile again, stamped now, once the sun has moved too far."""
        if self.last_tile_msg is None or self.rendered_sun is None:
            return
        now = self.get_clock().now()
        sun = self.sun_for(self.last_tile_msg, now.nanoseconds * 1e-9)
        moved = sun_separation(sun, self.rendered_sun)
        if moved > self.max_sun_change:
            self.get_logger().info(f"sun moved {moved:.1f} deg since the landmark was "
                                   "rendered: rendering it again")
            self.last_tile_msg.header.stamp = now.to_msg()
            self.on_tile(self.last_tile_msg)

    def on_render_view(self, request, response):
        """Perspective render of the current tile for a requested camera and pose."""
        response.success = False
        if self.last_tile_msg is None:
            response.message = "no DEM tile received yet"
            return response
        try:
            k, _d, _model, (width, height) = cv.camera_info_to_intrinsics(request.camera_info)
            if max(width, height) > self.max_size:
                raise ValueError(f"a {width}x{height} px view: at most {self.max_size} px a "
                                 "side (max_image_size)")
            camera = PinholeCamera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
            p, q = request.pose.position, request.pose.orientation
            from scipy.spatial.transform import Rotation

            rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            sun = (request.sun_azimuth, request.sun_elevation) if request.sun_elevation > 0 \
                else self.sun_for(self.last_tile_msg)
            result = self.renderer.render_perspective(camera, (p.x, p.y, p.z), rotation, sun)
        except (cv.ConversionError, RendererError, ValueError) as err:
            response.message = str(err)
            return response
        except Exception as err:   # any other failure: this request fails, the node serves on
            response.message = f"{type(err).__name__}: {err}"
            self.get_logger().error(f"render_view failed: {response.message}")
            return response
        header = cv.make_header(self.get_clock().now().to_msg(), "camera_optical")
        response.image = cv.array_to_image(display_u8(result.grey), "mono8", header)
        response.terrain_height = cv.array_to_image(
            result.hit_enu[..., 2].astype(np.float32), "32FC1", header)
        response.success = True
        response.message = f"{width}x{height} px, {result.mask.mean():.0%} terrain"
        return response

    def close(self) -> None:
        self.renderer.release()


def main(args=None):
    return run(LandmarkRendererNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
