"""A ROS 2 node that publishes a moiré sensor's wrench, with a `tare` service.

It opens the sensor in its own process (`moirejax.open_sensor`: a background thread owns
the camera and inverts every frame) and publishes every record:

| topic (relative to the node's namespace) | type | what |
|---|---|---|
| `wrench` | `geometry_msgs/msg/WrenchStamped` | the wrench of each record that carries a reading |
| `record` | `std_msgs/msg/String` | every record as its JSON line: status, covariance, contact |

and serves

| service | type | what |
|---|---|---|
| `tare` | `std_srvs/srv/Trigger` | a new no-contact reference from the next untouched frames |

The wrench is in the moirejax convention (N and N·m; x along the image columns, y up the
image, z into the sensor, so pressing is +Fz; torques about the image centre on the contact
surface) in the TF frame named by `--frame-id`, stamped with the frame's capture time. A
record whose status is not a reading (a frame the inversion could not read or did not
believe) publishes no wrench, never a zero one: its status is on `record`. An untouched
sensor publishes a zero wrench (status `no_contact`), as a force/torque driver does.

Run it where ROS 2 is installed (rclpy, geometry_msgs, std_msgs and std_srvs come with ROS,
not from PyPI), in an environment with moirejax:

    python examples/ros2_node.py --device fit.json --source 0 --frame-id left_pad
    python examples/ros2_node.py --device fit.json --source "HD Pro Webcam C920" \
        --ros-args -r __ns:=/left_finger
    ros2 topic echo /left_finger/wrench
    ros2 service call /left_finger/tare std_srvs/srv/Trigger

`--source sim` runs the simulated sensor, with no camera. The module imports ROS only inside
`main`, so that `wrench_message` can be used and tested without ROS.
"""

import argparse
import math
import sys

import moirejax as mj
import moirejax.live


def wrench_message(record: mj.live.WrenchRecord) -> dict | None:
    """The `geometry_msgs/msg/WrenchStamped` of a record, as nested dicts; `None` when the
    record carries no reading (a status outside `moirejax.live.WRENCH_STATUSES`: an
    estimate of the load, or the zero of an untouched sensor) or its wrench is not finite.

    **Arguments:**

    - `record`: a record of the sensor handle.

    **Returns:** `{"header": {"stamp": {"sec", "nanosec"}, "frame_id"}, "wrench": {"force":
    {"x", "y", "z"}, "torque": {"x", "y", "z"}}}` with the record's capture time, frame and
    wrench, or `None`.
    """
    wrench = record.wrench
    if record.status not in mj.live.WRENCH_STATUSES or wrench is None or not all(math.isfinite(v) for v in wrench):
        return None
    if not math.isfinite(record.stamp):
        return None
    # Whole seconds and the fraction apart: a Unix time in nanoseconds is beyond float64's digits.
    sec = math.floor(record.stamp)
    sec, nanosec = divmod(sec * 1_000_000_000 + round((record.stamp - sec) * 1e9), 1_000_000_000)
    force, torque = (dict(zip("xyz", (float(v) for v in part))) for part in (wrench[:3], wrench[3:]))
    return {
        "header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": record.frame_id},
        "wrench": {"force": force, "torque": torque},
    }


def main(argv: list[str] | None = None) -> int:
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rclpy.node import Node
    from rclpy.utilities import remove_ros_args
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    argv = sys.argv if argv is None else argv
    parser = argparse.ArgumentParser(description="Publish a moire sensor's wrench on ROS 2.")
    parser.add_argument("--device", required=True, help="the unit's (calibrated) device JSON")
    parser.add_argument("--source", default="sim", help="sim, a camera index, name or serial, a video or a folder")
    parser.add_argument("--sensor-id", default="moirejax", help="the records' sensor name")
    parser.add_argument("--frame-id", default="moirejax_sensor", help="TF frame of the wrench")
    args = parser.parse_args(remove_ros_args(argv)[1:])

    rclpy.init(args=argv)
    node = Node("moirejax_sensor")
    wrench_publisher = node.create_publisher(WrenchStamped, "wrench", 10)
    record_publisher = node.create_publisher(String, "record", 10)
    device, _ = mj.load_calibrated(args.device)
    node.get_logger().info(f"opening {args.source} (compiling the inversion takes a while)")
    sensor = mj.open_sensor(device, args.source, sensor_id=args.sensor_id, frame_id=args.frame_id)

    def publish(record: mj.live.WrenchRecord) -> None:
        # Called on the sensor's thread for every record; rclpy's publishers are thread-safe.
        record_publisher.publish(String(data=record.to_json()))
        fields = wrench_message(record)
        if fields is None:
            return
        message = WrenchStamped()
        message.header.stamp.sec = fields["header"]["stamp"]["sec"]
        message.header.stamp.nanosec = fields["header"]["stamp"]["nanosec"]
        message.header.frame_id = fields["header"]["frame_id"]
        for part in ("force", "torque"):
            vector = getattr(message.wrench, part)
            vector.x, vector.y, vector.z = (fields["wrench"][part][c] for c in "xyz")
        wrench_publisher.publish(message)

    def tare(request, response):
        # The tare waits for untouched frames (a fraction of a second) and refuses while
        # the sensor is touched.
        try:
            sensor.tare()
        except (RuntimeError, TimeoutError, ValueError) as e:
            response.success, response.message = False, str(e)
        else:
            response.success, response.message = True, "new no-contact reference taken"
        return response

    node.create_service(Trigger, "tare", tare)
    sensor.on_record(publish)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        sensor.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
