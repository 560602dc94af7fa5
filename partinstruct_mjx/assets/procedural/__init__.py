"""Procedural, part-annotated table-top objects for the 14 PartInstruct categories, in PartNet-Mobility layout.

`generate(out_dir, seed, instances, categories)` writes the library; `build_object` gives one in-memory instance;
`CATEGORIES` lists each category's PartNet name, allowed part labels and graspable parts.
"""

from partinstruct_mjx.assets.procedural.categories import CATEGORIES, Category
from partinstruct_mjx.assets.procedural.generator import build_object, generate, object_id, resolve_categories
from partinstruct_mjx.assets.procedural.partnet_writer import write_partnet
from partinstruct_mjx.assets.procedural.spec import Joint, Link, ObjectSpec, Part, Piece

__all__ = [
    "CATEGORIES", "Category", "Joint", "Link", "ObjectSpec", "Part", "Piece", "build_object", "generate",
    "object_id", "resolve_categories", "write_partnet",
]
