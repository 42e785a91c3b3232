"""The Foxglove live view: the hub speaks the Foxglove WebSocket protocol (foxglove-sdk), so
Foxglove and Lichtblick connect to it live (`fleetdaq.hub.live.foxglove.service.FoxgloveLive`)."""
