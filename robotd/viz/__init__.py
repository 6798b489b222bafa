"""The robot as Foxglove sees it: the live view served by the daemon, MCAP recordings, replays you can scrub.

Public API: `live.LiveViewer` (the daemon's viewer: enqueue from the loop, publish from a thread; `live.viewer_for`,
`live.Tee`), `publisher.Publisher` (messages on `channels.Channels`), `mcaplog` (read, write and convert the sensor
log as MCAP), `player.McapPlayer` (an MCAP file served with playback controls), `logtopics` (the log's records as
channels), `frames` and `scene` (pure geometry and messages).
"""
