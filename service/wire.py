"""The names on the wire: media types, columns and headers of the HTTP API.

Standard library only: the service (:mod:`service.formats`, :mod:`service.app`) and the SDK
(:mod:`clients.sdk`, which must import fast) both read them from here.
"""

JSON = "application/json"
ARROW = "application/vnd.apache.arrow.stream"
PARQUET = "application/vnd.apache.parquet"
NPZ = "application/x-npz"
GEOJSON = "application/geo+json"
PNG = "image/png"
PARQUET_ALIASES = (PARQUET, "application/x-parquet")

ENU_COLUMNS = ("x", "y", "z")
WGS84_COLUMNS = ("lat", "lon", "alt_m")
VELOCITY_COLUMNS = ("ve", "vn", "vu")
STD_COLUMNS = ("std_e", "std_n", "std_u")
#: a row's track (string or integer id) and its time (seconds): the service weighs the
#: correlated rows of one track itself (:func:`bdf.ingest.track_weights`)
TRACK_COLUMNS = ("track", "t")
#: the columns a binary body may hold: an upload's, a query's (anything else is a 422)
UPLOAD_COLUMNS = frozenset(
    (*ENU_COLUMNS, *WGS84_COLUMNS, *VELOCITY_COLUMNS, "input_noise_std", "sample_weight", *TRACK_COLUMNS)
)
QUERY_COLUMNS = frozenset((*ENU_COLUMNS, *WGS84_COLUMNS, "heading_deg"))

#: the region version a map answer comes from, and how far it is behind the newest
VERSION_HEADER = "X-Region-Version"
VERSIONS_BEHIND_HEADER = "X-Region-Versions-Behind"
SECONDS_BEHIND_HEADER = "X-Region-Seconds-Behind"
#: the maps of the region the answering process finished since then: at most 1, as each
#: refresh computes the newest version when it begins (the one under way then is behind)
REFRESHES_BEHIND_HEADER = "X-Region-Refreshes-Behind"
#: nats the map's "auto" hyperparameters lack from its data's evidence maximum (0: settled)
EVIDENCE_GAP_HEADER = "X-Region-Evidence-Gap"
REQUEST_ID_HEADER = "X-Request-ID"
IDEMPOTENCY_HEADER = "Idempotency-Key"
