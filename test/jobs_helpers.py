"""Jobs for test_jobs.py, in a module of their own: a worker process imports it to run them, and it
imports nothing heavy."""
import hashlib
import os

import numpy as np


def draw(context, job):
    """A seeded draw scaled by ``context['scale']``, the sha256 of the file that travelled in
    ``context['blob']`` (as the worker reads it) and the process that ran the job."""
    blob = context.get('blob')
    digest = hashlib.sha256(blob.path().read_bytes()).hexdigest() if blob is not None else None
    return float(np.random.default_rng(job).standard_normal()
                 * context['scale']), digest, os.getpid()


def fail_on_three(context, job):
    if job == 3:
        raise ArithmeticError(f'job {job} failed')
    return job
