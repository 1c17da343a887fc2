"""metamap: the on-board DEM tile server (dissertation 2.1).

Loads the mission's DEMs once, then

* answers ``/metamap/get_tile`` (terrain_nav_msgs/srv/GetDemTile) for any centre (ENU or
  WGS84), size and GSD, with ``success=false`` and the reason for a tile outside the DEMs;
* publishes a latched ``/metamap/tile`` around the predicted position from ``/nav/odometry``
  whenever the aircraft nears the edge of the last tile, sized from the horizontal position
  uncertainty plus the camera footprint.

The algorithms live in :mod:`terrain_nav_ros.core.terrain.metamap` and
:mod:`.core.terrain.tile_policy`.
"""

from __future__ import annotations

import math
import os

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.node import Node

from terrain_nav_msgs.msg import DemTile as DemTileMsg
from terrain_nav_msgs.srv import GetDemTile

from ..core.terrain.dem_io import DemError, dem_files
from ..core.terrain.dem_sources import open_dem_source
from ..core.terrain.geodesy import EnuOrigin
from ..core.terrain.metamap import MetaMap
from ..core.terrain.tile_policy import TilePolicy
from . import conversions as cv
from .ros_common import (
    LATCHED_QOS,
    RELIABLE_QOS,
    check_parameters_known,
    contained,
    declare,
    reject_all_changes,
    run,
)

# GDAL's default block cache (5% of RAM) would dominate the node's memory on tiled GeoTIFFs.
os.environ.setdefault("GDAL_CACHEMAX", "64")

#: The tile GSDs served, by parameter and by request [m/px].
GSD_RANGE = (0.01, 1000.0)


class MetamapNode(Node):
    """Serves and publishes DEM tiles on north-up grids of the mission ENU frame."""

    def __init__(self):
        super().__init__("metamap")
        files = [f for f in declare(self, "dem_files", [""],
                                    "DEM files, folders or globs (.asc .tif .hgt .npz), or "
                                    "'synthetic:seed=N,size=N,gsd=X'; empty = the embedded "
                                    "USGS Jacksboro DEM") if f]
        lat = declare(self, "origin_latitude", math.nan,
                      "mission ENU origin latitude [deg WGS84]; NaN = centre of the first DEM")
        lon = declare(self, "origin_longitude", math.nan, "mission ENU origin longitude [deg]")
        alt = declare(self, "origin_altitude", 0.0, "ENU origin ellipsoidal height [m]")
        undulation = declare(self, "geoid_undulation", 0.0,
                             "geoid height N at the origin [m]: DEM (orthometric) heights "
                             "become ellipsoidal as H + N")
        self.gsd = declare(self, "gsd", 5.0, "default tile ground sample distance [m/px]",
                           min_value=GSD_RANGE[0], max_value=GSD_RANGE[1])
        self.frame_id = declare(self, "frame_id", "map", "frame of the tiles (REP 105)")
        interpolation = declare(self, "interpolation", "spline",
                                "spline | bicubic | bilinear | nearest | idw (dissertation "
                                "2.1.3); spline is smooth enough for shading finer than the DEM")
        fill = declare(self, "fill_voids", True, "fill small DEM voids before sampling")
        self.policy = TilePolicy(
            min_size=declare(self, "min_tile_size", 256, "smallest published tile [px]",
                             min_value=16, max_value=8192),
            max_size=declare(self, "max_tile_size", 1024, "largest published tile [px]",
                             min_value=16, max_value=8192),
            footprint_radius=declare(self, "camera_footprint_radius", 600.0,
                                     "radius of the camera's ground footprint [m]",
                                     min_value=0.0),
            sigma_scale=declare(self, "sigma_scale", 3.0,
                                "position sigmas added to the footprint", min_value=0.0),
            lookahead=declare(self, "lookahead", 5.0,
                              "predict the position this far ahead [s]", min_value=0.0),
            margin=declare(self, "tile_margin", 1.5,
                           "a new tile covers this many times the needed radius "
                           "(hysteresis)", min_value=1.0),
        )
        self.default_size = declare(self, "tile_size", 512, "default service tile size [px]",
                                    min_value=1, max_value=8192)
        self.max_request = declare(self, "max_service_tile_size", 8192,
                                   "largest side of a tile the service serves [px] (a "
                                   "8192 px float32 tile is 256 MB)", min_value=16,
                                   max_value=16384)
        initial = declare(self, "initial_tile", True,
                          "publish a tile around the ENU origin at start-up, before any "
                          "odometry (lets the EKF learn the origin from it)")
        check_parameters_known(self)  # before the DEMs are read
        self.add_on_set_parameters_callback(reject_all_changes)

        named = [f for f in files if f.startswith(("synthetic", "jacksboro", "matplotlib:"))]
        paths = dem_files([f for f in files if f not in named])
        dems = [open_dem_source(f) for f in named + paths] if files else [open_dem_source("")]
        origin = (EnuOrigin(lat, lon, alt, undulation) if np.isfinite(lat) and np.isfinite(lon)
                  else None)
        self.metamap = MetaMap(dems, origin, interpolation=interpolation, fill_voids=fill,
                               heights="enu")
        o = self.metamap.origin
        self.enu_origin = (o.lat, o.lon, o.alt)
        self.source_crs = str(dems[0].crs) if dems[0].crs is not None else "local"
        self.tile_pub = self.create_publisher(DemTileMsg, "metamap/tile", LATCHED_QOS)
        self.create_service(GetDemTile, "metamap/get_tile", self.on_get_tile)
        self.create_subscription(Odometry, "nav/odometry", self.on_odometry, RELIABLE_QOS)
        self.get_logger().info(
            f"loaded {', '.join(d.name for d in dems)}; ENU origin {o.lat:.6f}, {o.lon:.6f}; "
            f"native GSD {self.metamap.native_gsd:.1f} m")
        for d in dems:
            if d.warning:  # impossible heights (corrupt pixels?) read as voids
                self.get_logger().warning(d.warning)
        self._initial_timer = self.create_timer(0.2, self._publish_initial_tile) \
            if initial else None

    def _publish_initial_tile(self) -> None:
        # Wait for a valid clock: with use_sim_time the time is 0 until /clock arrives, and
        # the tile's stamp sets the renderer's sun.
        if self.get_clock().now().nanoseconds == 0:
            return
        self._initial_timer.cancel()
        if self.policy.current is not None:
            return  # odometry came first
        georef = self.policy.update((0.0, 0.0), (0.0, 0.0), np.zeros((2, 2)), self.gsd)
        try:
            self.tile_pub.publish(self._tile_msg(self.metamap.tile(georef),
                                                 self.get_clock().now().to_msg()))
        except DemError as err:
            self.policy.forget()
            self.get_logger().warning(f"no initial tile at the origin: {err}")

    def _tile_msg(self, tile, stamp) -> DemTileMsg:
        return cv.dem_tile_to_msg(tile.elevation, tile.georef, cv.make_header(stamp, self.frame_id),
                                  self.enu_origin, "ENU up of the mission origin (WGS84)",
                                  self.source_crs)

    def on_get_tile(self, request, response):
        """Serve a tile; any failure becomes success=false with the reason."""
        try:
            gsd = request.gsd or self.gsd
            width = request.width or self.default_size
            height = request.height or self.default_size
            if max(width, height) > self.max_request:
                raise ValueError(f"a {width}x{height} px tile: at most {self.max_request} px "
                                 "a side (max_service_tile_size)")
            if not GSD_RANGE[0] <= gsd <= GSD_RANGE[1]:
                raise ValueError(f"gsd {gsd} m/px: must be within {GSD_RANGE[0]:g}-"
                                 f"{GSD_RANGE[1]:g}")
            if request.center_frame == GetDemTile.Request.CENTER_GEODETIC:
                tile = self.metamap.tile_at_geodetic(request.center_x, request.center_y, gsd,
                                                     width, height)
            elif request.center_frame == GetDemTile.Request.CENTER_ENU:
                tile = self.metamap.tile_at(request.center_x, request.center_y, gsd, width,
                                            height)
            else:
                raise ValueError(f"unknown center_frame {request.center_frame}")
            response.tile = self._tile_msg(tile, self.get_clock().now().to_msg())
            response.success = True
            response.message = f"{width}x{height} px at {gsd} m/px"
        except (DemError, ValueError) as err:
            response.success = False
            response.message = str(err)
            self.get_logger().warning(f"get_tile refused: {err}")
        except Exception as err:    # any other failure: this request fails, the node serves on
            response.success = False
            response.message = f"{type(err).__name__}: {err}"
            self.get_logger().error(f"get_tile failed: {response.message}")
        return response

    @contained
    def on_odometry(self, msg: Odometry) -> None:
        """Publish a new tile when the predicted footprint leaves the current one."""
        if msg.header.frame_id != self.frame_id:
            self.get_logger().warning(f"odometry in {msg.header.frame_id or '(none)'}, not "
                                      f"{self.frame_id}: ignored", throttle_duration_sec=5.0)
            return
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        cov = cv.covariance_to_array(msg.pose.covariance, 6)
        values = (p.x, p.y, v.x, v.y, cov[0, 0], cov[1, 1])
        if not all(math.isfinite(x) for x in values):
            self.get_logger().warning("odometry with non-finite values ignored",
                                      throttle_duration_sec=5.0)
            return
        georef = self.policy.update((p.x, p.y), (v.x, v.y), cov[:2, :2], self.gsd)
        if georef is None:
            return
        try:
            self.tile_pub.publish(self._tile_msg(self.metamap.tile(georef), msg.header.stamp))
            self.get_logger().info(
                f"tile {georef.width}x{georef.height} px centred at "
                f"({georef.centre[0]:.0f}, {georef.centre[1]:.0f}) m")
        except DemError as err:
            self.policy.forget()
            self.get_logger().warning(f"no tile around the aircraft: {err}",
                                      throttle_duration_sec=5.0)


def main(args=None):
    return run(MetamapNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
