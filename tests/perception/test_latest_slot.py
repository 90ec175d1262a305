"""The detector's one-frame slot counts every frame it drops against the gap the frame fell in.

A detection's ``dropped`` figure is what the recorder and the adaptation bench use to say which frames
between two processed ones the detector replaced while busy (kgadapt.operator.timeline.attribute_losses). The
count must be the one at the moment a frame is taken: frames replaced while that frame is being worked
on are newer than it, so they belong to the gap after it, not before.
"""

from __future__ import annotations

import threading

from kgadapt.onboard.perception.detector import LatestSlot


def test_the_difference_of_two_takes_counts_is_exactly_the_frames_lost_between_them():
    slot = LatestSlot()
    slot.put(1)
    assert slot.take(timeout=0) == 1
    first = slot.replaced_when_taken
    # Frame 1 is slow to process (a hedge, a stolen CPU): 2..6 arrive meanwhile; 2..5 are replaced.
    for seq in range(2, 7):
        slot.put(seq)
    after_work_on_1 = slot.replaced  # what a count read when 1's detections are published would say
    assert slot.take(timeout=0) == 6
    second = slot.replaced_when_taken
    # Frame 6 is quick: one frame (7) comes in and is taken next, nothing replaced.
    slot.put(7)
    assert slot.take(timeout=0) == 7
    third = slot.replaced_when_taken
    assert second - first == 4  # 2, 3, 4, 5: every frame between 1 and 6
    assert third - second == 0  # none between 6 and 7
    # Read after the work instead, the four drops land on frame 1 and the gap 1..6 shows none of them.
    assert second - after_work_on_1 == 0


def test_a_count_is_taken_with_its_frame_even_while_frames_keep_coming():
    slot = LatestSlot()
    stop = threading.Event()
    sent: list[int] = []

    def camera() -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            sent.append(seq)
            slot.put(seq)

    thread = threading.Thread(target=camera, daemon=True)
    thread.start()
    try:
        taken: list[tuple[int, int]] = []
        while len(taken) < 200:
            item = slot.take(timeout=1.0)
            if item is not None:
                taken.append((item, slot.replaced_when_taken))
    finally:
        stop.set()
        thread.join(timeout=5)
    # Every frame between two taken ones was replaced in the slot, and the counts say exactly how many.
    for (seq_a, count_a), (seq_b, count_b) in zip(taken, taken[1:]):
        assert count_b - count_a == seq_b - seq_a - 1, (seq_a, count_a, seq_b, count_b)
