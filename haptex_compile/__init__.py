"""haptex compiler: texture sources -> tactile assets (HAPTEX method)."""
import os as _os

# OpenCV on one thread (a user's setting wins): its worker threads are not fork-safe, and the
# tools fork workers (see haptex_compile.forked_map, which also sets it where cv2 came first).
_os.environ.setdefault("OPENCV_FOR_THREADS_NUM", "1")

__version__ = "0.1.0"
