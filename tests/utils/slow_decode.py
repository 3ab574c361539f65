"""Decode functions for the decoder pool's tests: module-level, so a spawned worker process can import them."""
import time


def sleepy_read(staged, pose_topic=None, imu_topic=None):
    """A decode that never finishes in time (it sleeps far past any limit the tests set)."""
    time.sleep(60)
    raise AssertionError("not reached")
