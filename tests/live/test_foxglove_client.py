"""The tests' Foxglove client against hil's live view (the foxglove-sdk server): a subscription
the server refuses as an unknown channel is sent again once, in the words the server uses."""

from __future__ import annotations

from hil.core.recording.live import LiveSink
from tests.live.foxglove_client import FoxgloveClient

SCHEMA = {"title": "a", "type": "object", "properties": {"x": {"type": "number"}}}


def test_a_refused_subscription_is_sent_again_once_and_the_others_are_served() -> None:
    sink = LiveSink(port=0, rates={"/a": 0})
    try:
        sink.add_topic("a", "/a", SCHEMA)
        client = FoxgloveClient(sink.url)
        assert client.wait_for(lambda: "/a" in client.topics(), 10)
        # a channel the client was advertised that the server does not know (yet): as in
        # the server's race, where its table is filled just after the advertise is sent
        ghost = max(client.channels) + 100
        client.channels[ghost] = {"id": ghost, "topic": "/ghost"}
        client.subscribe(["/a", "/ghost"])
        refused = f"Unknown channel ID: {ghost}"
        assert client.wait_for(
            lambda: sum(s["message"] == refused for s in client.statuses) == 2, 10)
        assert client.resubscribed == {ghost}
        assert client.wait_for(lambda: sink.log("a", 1, {"x": 1.0}) or
                               client.messages.get("/a"), 10)
        assert client.messages["/a"][0] == (1, {"x": 1.0})
        assert not client.wait_for(
            lambda: sum(s["message"] == refused for s in client.statuses) > 2, 0.5)
        client.close()
    finally:
        sink.close()
