"""The operator's tools: ``kgadapt status``, ``demo``, ``certs``, ``fleet``, the cluster and the timeline.

Runtime code (they ship in the wheel), built on the parts; none of the parts imports them.
"""
