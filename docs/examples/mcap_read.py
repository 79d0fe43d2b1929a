"""The final labels of slides.mcap (tactiled export), with their sensor index and confidence."""
import json

from mcap.reader import make_reader

with open("slides.mcap", "rb") as fh:
    for _schema, channel, message in make_reader(fh).iter_messages(topics=["/tactiled/fingertip0/roughness"]):
        body = json.loads(message.data)
        if body["final"]:
            print(channel.topic, body["slide_id"], body["start"], body["label"], body["confidence"])
