"""The store: records as WebDataset tar shards plus a zarr v3 index, written and read by one schema.

- :mod:`hoidata.store.codec`: one record's members <-> bytes (``encode_record``, ``decode_record``)
- :mod:`hoidata.store.shards`: deterministic tar shards, written atomically (``write_shard``,
  ``ShardWriter``) and read strictly (``read_shard_members``, ``iter_records``)
- :mod:`hoidata.store.index`: the zarr index (``write_index``, ``read_index``)
- :mod:`hoidata.store.paths`: local or remote (``resolve_store``), leftovers of unfinished writes, the index lock
- :mod:`hoidata.store.remote`: stores at http(s)://, s3://, gs:// URLs, read through fsspec (``RemoteStore``)
- :mod:`hoidata.store.httpread`: http(s) files read in range-request blocks, resumed, under idle timeouts
  (``HttpReader``, ``RemoteOptions``)
- :mod:`hoidata.store.spans`: each record's byte span in its shard, for reading records in any order
  (``record_spans``; ``read_record`` reads one back)
- :mod:`hoidata.store.verify`: integrity (``verify_store``) and the shards a resumed build keeps
- :mod:`hoidata.store.inspect`: a PNG contact sheet of a store

The names most callers need are re-exported here.
"""

from hoidata.store.codec import (
    FRAME_IMAGE,
    KEY,
    MAX_IMAGE_SIDE,
    MAX_MEMBER_BYTES,
    decode_record,
    encode_record,
)
from hoidata.store.index import (
    INDEX_NAME,
    ShardInfo,
    StoreIndex,
    index_labels,
    read_index,
    shard_name,
    to_jsonable,
    write_index,
)
from hoidata.store.paths import index_lock, local_store, resolve_store, stale_temps
from hoidata.store.remote import UNKNOWN_SIZE, RemoteFile, RemoteStore
from hoidata.store.shards import (
    ShardWriter,
    iter_records,
    read_checked_shard,
    read_record,
    read_shard_members,
    record_member,
    shard_sizes,
    shard_source,
    sidecar_name,
    write_shard,
)
from hoidata.store.spans import record_spans
from hoidata.store.verify import (
    VerifyReport,
    completed_shards,
    file_digest,
    read_sidecar,
    verify_store,
)

__all__ = [
    "FRAME_IMAGE", "INDEX_NAME", "KEY", "MAX_IMAGE_SIDE", "MAX_MEMBER_BYTES", "RemoteFile", "RemoteStore", "ShardInfo",
    "ShardWriter", "StoreIndex", "UNKNOWN_SIZE", "VerifyReport", "completed_shards", "decode_record", "encode_record", "file_digest",
    "index_labels", "index_lock", "iter_records", "local_store", "read_checked_shard", "read_index",
    "read_record", "read_shard_members",
    "record_member", "record_spans", "read_sidecar", "resolve_store", "shard_name", "shard_sizes", "shard_source",
    "sidecar_name", "stale_temps", "to_jsonable", "verify_store", "write_index", "write_shard",
]
