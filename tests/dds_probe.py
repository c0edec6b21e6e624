"""A test helper process: ``writer`` publishes on /dds_probe and says which Fast DDS shared
memory and UDP addresses its process uses; ``reader`` counts what arrives within 8 s."""
import json
import os
import sys
import time

import rclpy
from std_msgs.msg import String


def udp_addresses() -> list:
    """Local addresses of this process's UDP sockets (from /proc/net/udp by socket inode)."""
    inodes = set()
    for fd in os.listdir('/proc/self/fd'):
        try:
            link = os.readlink(f'/proc/self/fd/{fd}')
        except OSError:
            continue
        if link.startswith('socket:['):
            inodes.add(link[8:-1])
    found = []
    with open('/proc/net/udp') as f:
        next(f)
        for line in f:
            cols = line.split()
            if cols[9] in inodes:
                ip = bytes.fromhex(cols[1].split(':')[0])[::-1]
                found.append('.'.join(str(b) for b in ip))
    return sorted(set(found))


def main(role: str) -> None:
    rclpy.init()
    node = rclpy.create_node(f'dds_probe_{role}')
    deadline = time.monotonic() + 8.0
    if role == 'reader':
        got = []
        node.create_subscription(String, 'dds_probe', got.append, 10)
        while time.monotonic() < deadline and len(got) < 20:
            rclpy.spin_once(node, timeout_sec=0.05)
        print(json.dumps({'received': len(got)}), flush=True)
        return
    pub = node.create_publisher(String, 'dds_probe', 10)
    while time.monotonic() < deadline and pub.get_subscription_count() == 0:
        rclpy.spin_once(node, timeout_sec=0.05)
    matched = pub.get_subscription_count()
    for _ in range(60):
        pub.publish(String(data='x'))
        time.sleep(0.05)
    with open('/proc/self/maps') as f:
        shm = sorted({line.split()[-1] for line in f if '/dev/shm/fast' in line})
    print(json.dumps({'matched': matched, 'shm': shm,
                      'udp': udp_addresses()}), flush=True)


if __name__ == '__main__':
    main(sys.argv[1])
