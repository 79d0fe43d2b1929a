"""Pull the raw outlet until two final label markers came; check the stamps increase; count the loss markers."""
import json

import pylsl

raw = pylsl.StreamInlet(pylsl.resolve_byprop("name", "tactiled-fingertip0", timeout=30)[0])
marks = pylsl.StreamInlet(pylsl.resolve_byprop("name", "tactiled-fingertip0-labels", timeout=30)[0])
raw.open_stream(timeout=10)
info = raw.info(timeout=10)  # keep it: the description lives in it
acq = info.desc().child("acquisition")
got, labels, lost, last, backwards = 0, [], [], None, 0
while len(labels) < 2:
    chunk, stamps = raw.pull_chunk(timeout=1.0)
    got += len(chunk)
    for t in stamps:
        backwards += last is not None and t <= last
        last = t
    markers, _ = marks.pull_chunk(timeout=0.0)
    for (text,) in markers:
        event = json.loads(text)
        if event["event"] == "lost":
            lost.append(event)
        elif event["final"]:
            labels.append(event)
print(f"sensor {acq.child_value('sensor_id')} at {acq.child_value('fs_firmware')} Hz: {got} samples, {backwards} stamps not increasing, "
      f"{len(lost)} loss markers; first label: {labels[0]['label']}")
