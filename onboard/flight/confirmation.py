"""Marker confirmation: only markers seen steadily, and of the site, become landing targets.

A detector reports every candidate it decodes, and on textures, ChArUco boards
or markers of another dictionary some candidates are phantoms: a code that
happens to decode in one frame, somewhere else in the next. A landing target
built from one would steer the quadcopter towards nothing. :class:`MarkerConfirmer`
passes a marker id on only once it has been seen in ``frames`` consecutive
frames at a consistent place (centre within ``max_shift`` of its side, side
within ``max_scale`` of the last), with its cells reading clean when the
detector says (``clean``, :func:`kgadapt.onboard.perception.markers.cells_are_clean`: a
6x6 marker or a ChArUco square that decodes as a 4x4 code does not), and,
when the site's marker set is known, only ids of that set. Detections themselves still carry every candidate.

**A moving vehicle.** Between two sightings a second apart, a vehicle that
accelerates towards its target moves the marker across the image by many of
its sides (ArduCopter SITL: no LANDING_TARGET for 3.6 s while the image rule
kept restarting the count). When the caller knows where each marker lies in
the local frame (:class:`Place`: the flight bridge places it from the
vehicle's attitude and position at the frame's time), steadiness is judged
there instead, and its size in the image may change as the vehicle descends.

How far a place may move between sightings comes from how well it was
measured, when the place says how (its line of sight, side in pixels, the
focal length, the vehicle's speed and turn rate): the distance from the
marker's size is uncertain by about ``distance * pixel_sigma / side_px``
along the line of sight (0.5 px on a 16 px marker 10 m away: 0.3 m; ArduCopter
SITL confirmed none of 7 such sightings with a fixed 2 % of the distance),
across it by ``distance * pixel_sigma / focal_px``, and in every direction by
the attitude's own error and the pose's timing (``timing_sigma_s`` times the
speed and the turn rate's sweep at that distance). The two places' spreads add,
and the move is steady within ``n_sigma`` of them (a Mahalanobis distance),
never less than ``max_shift`` of the side. A place without that information
may move ``max_shift`` of its side plus ``range_share`` of its distance.
Phantoms are kept out by identity (the site's ids, one dictionary, clean
cells), not by a tight place: a code that decodes by chance in consecutive
frames lies nowhere in particular. The spread allowed is wide only along
the line of sight (a 16 px marker at 10 m: about 1.5 m along it, 0.25 m
across it).

**A landing pad.** The markers of the site's pad (those with a ``position``,
:meth:`SiteMarkers.place_of`) are followed as one: their places are the pad's
landing point (the caller takes each marker's offset away), and in a frame
that shows several of them the largest in the image stands for the pad. A
descent that loses the big marker below half a metre and finds the small one
keeps its streak, where a streak per id would start again (3 s at 1 detection
a second).

The site's markers come from the knowledge graph or a site file (:mod:`kgadapt.onboard.flight.site`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Sequence

import msgspec

from kgadapt.onboard.flight.site import SiteMarkers, load_site  # noqa: F401  (load_site: where callers find it with the confirmer)
from kgadapt.shared import messages
from kgadapt.shared.errors import ConfigError, MessageError


@dataclass(frozen=True, kw_only=True)
class ConfirmationSettings:
    """How steady a marker must be before it counts."""

    frames: int = 3  # consecutive frames with the marker
    max_shift: float = 0.5  # centre moves at most this share of the marker's side between frames
    max_scale: float = 1.5  # side changes at most by this factor between frames
    max_missed: int = 1  # frames a confirmed or confirming marker may be missed without losing its streak ...
    max_gap_s: float = 1.5  # ... or seconds since it was last seen: a marker seen once a second keeps its streak
    site: SiteMarkers | None = None  # when known, other ids never confirm
    range_share: float = 0.02  # places without a measurement model: allowed error per metre of distance
    # The measurement model of places that carry one (module docstring):
    pixel_sigma: float = 0.5  # a corner's error, px (1 sigma)
    attitude_sigma_rad: float = 0.005  # the attitude's error from one sighting to the next (about 0.3 degrees)
    timing_sigma_s: float = 0.05  # the pose at the frame's time: stamps of arrival, not of capture
    n_sigma: float = 3.5  # steady within this many sigmas of the two places' spreads

    def __post_init__(self) -> None:
        if (self.frames < 1 or self.max_shift <= 0 or self.max_scale < 1 or self.max_missed < 0 or self.max_gap_s < 0
                or not 0 <= self.range_share < 0.5 or self.pixel_sigma < 0 or self.attitude_sigma_rad < 0
                or self.timing_sigma_s < 0 or self.n_sigma <= 0):
            raise ConfigError("confirmation: frames >= 1, max_shift > 0, max_scale >= 1, max_missed >= 0, "
                              "max_gap_s >= 0, 0 <= range_share < 0.5, pixel_sigma, attitude_sigma_rad and "
                              "timing_sigma_s >= 0, n_sigma > 0")


class Place(NamedTuple):
    """Where a marker lies in the local frame (NED, m), its side (m) and its distance from the camera (m).

    The rest says how it was measured, for its uncertainty (0 / None: unknown): the line of sight
    (unit, NED), the marker's side in the image and the focal length (px), and the vehicle's speed
    (m/s) and turn rate (rad/s) at the frame's time.
    """

    ned: tuple[float, float, float]
    size_m: float
    range_m: float
    los: tuple[float, float, float] | None = None
    side_px: float = 0.0
    focal_px: float = 0.0
    speed_mps: float = 0.0
    rate_rad_s: float = 0.0


@dataclass
class _Track:
    centre: tuple[float, float]
    side: float
    streak: int
    last_frame: float
    missed: int = 0
    place: Place | None = None


@dataclass
class MarkerConfirmer:
    """Follows marker ids over frames; :meth:`update` returns the indices of confirmed markers."""

    settings: ConfirmationSettings = field(default_factory=ConfirmationSettings)
    _tracks: dict[int, _Track] = field(default_factory=dict, repr=False)
    _last_frame: float = field(default=-math.inf, repr=False)
    refused_off_site: int = 0  # candidates of ids the site does not have
    unconfirmed: int = 0  # candidates not (yet) steady
    refused_unclean: int = 0  # candidates whose cells did not read clean (the detector says so)

    def update(self, ids: Sequence[Any], corners: Sequence[Any], frame_time: float,
               clean: Sequence[Any] | None = None,
               places: Sequence[Place | None] | None = None) -> list[int] | None:
        """Feed one frame's detections; the indices of the markers confirmed in it.

        ``places`` (parallel to ``ids``, None where unknown): where each marker lies in
        the local frame; steadiness is then judged there (see the module docstring).
        None when the frame is not newer than the last one fed (a second detector
        answering for the same frame during a migration): it neither confirms
        nor breaks a streak.
        """
        # Check everything before changing any state: a malformed message changes nothing.
        parsed = []
        for index, (raw_id, c) in enumerate(zip(ids, corners, strict=True)):
            mid = raw_id[0] if isinstance(raw_id, list) and len(raw_id) == 1 else raw_id
            geometry = _geometry(c)
            if not isinstance(mid, int) or isinstance(mid, bool) or geometry is None:
                raise MessageError(f"detections marker {index}: need an integer id and 4 [x, y] corners")
            parsed.append((index, mid, geometry))
        if frame_time <= self._last_frame:
            return None
        self._last_frame = frame_time
        site = self.settings.site
        # Tracks are kept per landing point: the markers of one pad (SiteMarkers.place_of) are one track, so a
        # descent that loses the big marker and finds the small one keeps its streak (their places agree).
        groups: dict[int, list[tuple[int, int, tuple[float, float], float]]] = {}
        for index, mid, (centre, side) in parsed:
            if site is not None and mid not in site.sizes_m:
                self.refused_off_site += 1
                continue
            if clean is not None and index < len(clean) and clean[index] is False:
                self.refused_unclean += 1
                continue  # not counted as seen: its streak, if any, takes a miss
            groups.setdefault(site.place_of(mid) if site is not None else mid, []).append((index, mid, centre, side))
        seen: dict[int, tuple[int, tuple[float, float], float]] = {}
        placed: dict[int, Place | None] = {}
        for key, group in groups.items():
            ids_in = [mid for _, mid, _, _ in group]
            index, _, centre, side = max(group, key=lambda g: g[3])  # the pad's largest marker in the image
            if len(set(ids_in)) < len(ids_in):  # the same id twice in one frame: none of the place is trusted
                seen[key], placed[key] = (-1, centre, side), None
                continue
            seen[key] = (index, centre, side)
            placed[key] = places[index] if places is not None and index < len(places) else None
        confirmed = []
        for mid, (index, centre, side) in seen.items():
            track = self._tracks.get(mid)
            place = placed[mid]
            steady = track is not None and index >= 0 and self._steady(track, centre, side, place)
            streak = track.streak + 1 if steady and track is not None else (1 if index >= 0 else 0)
            self._tracks[mid] = _Track(centre, side, streak, frame_time, place=place)  # seen: missed starts over
            if index >= 0 and streak >= self.settings.frames:
                confirmed.append(index)
            elif index >= 0:
                self.unconfirmed += 1
        for mid in [m for m in self._tracks if m not in seen]:
            track = self._tracks[mid]
            track.missed += 1
            if track.missed > self.settings.max_missed and frame_time - track.last_frame > self.settings.max_gap_s:
                del self._tracks[mid]  # missed too often and too long: the streak is broken
        return sorted(confirmed)

    def _steady(self, track: _Track, centre: tuple[float, float], side: float, place: Place | None) -> bool:
        s = self.settings
        if place is not None and track.place is not None:  # in the local frame: the vehicle's motion taken out
            size = max(place.size_m, track.place.size_m)
            move = [a - b for a, b in zip(place.ned, track.place.ned, strict=True)]
            if math.hypot(*move) <= s.max_shift * size:
                return True
            spreads = [self._spread(p) for p in (place, track.place)]
            if spreads[0] is None or spreads[1] is None:
                return math.hypot(*move) <= s.max_shift * size + s.range_share * max(place.range_m, track.place.range_m)
            summed = [[a + b for a, b in zip(r0, r1, strict=True)] for r0, r1 in zip(*spreads, strict=True)]
            return _mahalanobis2(move, summed) <= s.n_sigma ** 2
        return (math.dist(centre, track.centre) <= s.max_shift * max(side, track.side)
                and max(side, track.side) <= s.max_scale * min(side, track.side))

    def _spread(self, place: Place) -> list[list[float]] | None:
        """The place's covariance (m², NED) from how it was measured; None when it does not say."""
        s = self.settings
        if place.los is None or place.side_px <= 0 or place.focal_px <= 0:
            return None
        d = place.range_m
        along = d * s.pixel_sigma / place.side_px  # the distance from the marker's size in pixels
        across = d * s.pixel_sigma / place.focal_px  # its centre's direction
        pose = math.hypot(d * s.attitude_sigma_rad, s.timing_sigma_s * place.speed_mps,
                          s.timing_sigma_s * place.rate_rad_s * d)
        los = place.los
        return [[(along ** 2 - across ** 2) * los[i] * los[j] + (across ** 2 + pose ** 2) * (i == j)
                 for j in range(3)] for i in range(3)]

    def keep(self, detections: messages.Detections, frame_time: float,
             places: Sequence[Place | None] | None = None) -> messages.Detections | None:
        """A ``detections`` message cut down to its confirmed markers (None: not a newer frame).

        ``poses``, when present, is cut the same way.
        """
        ids, corners = detections.ids, detections.corners
        if len(ids) != len(corners):
            raise MessageError(f"detections has {len(ids)} ids but {len(corners)} corner sets")
        indices = self.update(ids, corners, frame_time, detections.clean, places)
        if indices is None:
            return None
        poses = detections.poses
        if isinstance(poses, list) and len(poses) == len(ids):
            poses = [poses[i] for i in indices]
        return msgspec.structs.replace(detections, ids=[ids[i] for i in indices],
                                       corners=[corners[i] for i in indices], poses=poses)


def _mahalanobis2(v: Sequence[float], cov: Sequence[Sequence[float]]) -> float:
    """vᵀ cov⁻¹ v for a 3x3 covariance (inf when it is singular)."""
    (a, b, c), (d, e, f), (g, h, i) = cov
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if det <= 0:
        return math.inf
    inv = [[e * i - f * h, c * h - b * i, b * f - c * e],
           [f * g - d * i, a * i - c * g, c * d - a * f],
           [d * h - e * g, b * g - a * h, a * e - b * d]]
    return sum(v[r] * inv[r][k] * v[k] for r in range(3) for k in range(3)) / det


def _geometry(corners: Any) -> tuple[tuple[float, float], float] | None:
    try:
        pts = [(float(x), float(y)) for x, y in (corners[0] if len(corners) == 1 else corners)]
    except (TypeError, ValueError):
        return None
    if len(pts) != 4 or not all(math.isfinite(v) for p in pts for v in p):
        return None
    cx, cy = sum(p[0] for p in pts) / 4, sum(p[1] for p in pts) / 4
    side = sum(math.dist(pts[i], pts[(i + 1) % 4]) for i in range(4)) / 4
    return (cx, cy), side
