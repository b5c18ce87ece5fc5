"""2.x's discovery views (`pulicast.discovery`), on pulicast-rs's
discovery: `from pulicast_rs.discovery.node_discoverer import NodeDiscoverer`."""
