"""One distinctive sample of every terrain_nav_msgs message, and a publisher process for them.

``python message_samples.py`` publishes the samples on /samples/<Type> until interrupted;
test_messages.py receives them in another process and compares field by field.
"""

import numpy as np
from std_msgs.msg import Header

from terrain_nav_msgs.msg import Minutia, MinutiaArray, PvaFix
from terrain_nav_ros.core.terrain.georef import GeoReference as CoreGeoReference
from terrain_nav_ros.nodes import conversions as cv


def samples() -> dict:
    header = Header(stamp=cv.ns_to_stamp(1_700_000_000_123_456_789), frame_id="map")
    georef = CoreGeoReference(-1234.5, 987.25, 2.5, 6, 4)
    origin = (36.1, -84.2, 350.0)
    heights = np.arange(24, dtype=np.float32).reshape(4, 6) * 10.5
    heights[2, 3] = np.nan
    image = (np.arange(24, dtype=np.uint8) * 7).reshape(4, 6)
    mask = np.ones((4, 6), bool)
    mask[0, :2] = False
    fix = PvaFix(header=header, status=PvaFix.STATUS_POSITION_ATTITUDE, reason="ok",
                 relocalisation=True,
                 latitude=36.12345678, longitude=-84.87654321, altitude=1234.5,
                 pose=cv.pose_with_covariance([10.0, -20.0, 1500.0], [0.0, 0.0, 0.38268343,
                                               0.92387953], np.diag(np.arange(1.0, 7.0))),
                 velocity_valid=True, similarity=0.875, num_pairings=17,
                 num_camera_minutiae=60, num_landmark_minutiae=140)
    fix.velocity.x, fix.velocity.y, fix.velocity.z = 30.0, -1.5, 0.25
    fix.velocity_covariance = np.eye(3).ravel() * 4.0
    return {
        "GeoReference": cv.georef_to_msg(georef, origin, "EPSG:32616"),
        "Minutia": Minutia(x=1.5, y=-2.5, col=3.0, row=4.0, orientation=1.25,
                           type=Minutia.BIFURCATION, quality=0.5),
        "MinutiaArray": MinutiaArray(
            header=header, georef=cv.georef_to_msg(georef, origin), source=MinutiaArray.SOURCE_DEM,
            minutiae=[Minutia(x=float(i), y=-float(i), col=i + 0.5, row=i + 0.25,
                              orientation=0.125 * i, type=Minutia.ENDING, quality=0.75)
                      for i in range(5)], reason=""),
        "GeoImage": cv.geo_image_to_msg(image, georef, header, mask, origin),
        "DemTile": cv.dem_tile_to_msg(heights, georef, header, origin, "EGM96", "EPSG:4326"),
        "PvaFix": fix,
    }


def main():
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init()
    node = rclpy.create_node("sample_publisher")
    msgs = samples()
    pubs = {name: node.create_publisher(type(msg), f"/samples/{name}", 10)
            for name, msg in msgs.items()}
    node.create_timer(0.2, lambda: [pubs[n].publish(m) for n, m in msgs.items()])
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
