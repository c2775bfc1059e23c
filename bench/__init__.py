"""lidarmap's benchmark harness: accuracy and speed of the SLAM engine on logs with ground truth,
and maps of logs without (``python -m bench`` or ``lidarmap bench``; results under ``bench/results/``).

Every (log, seed) runs in its own child process, one after the other, so that wall time and peak
memory belong to that run alone.
"""
