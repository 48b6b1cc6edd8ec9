"""The data dexflow makes and reads: the demo generator (:mod:`dexflow.data.demo`), dataset
readers and adapters (:mod:`dexflow.data.readers`, :mod:`dexflow.data.adapters`).
"""
