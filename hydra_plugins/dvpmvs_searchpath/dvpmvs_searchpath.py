"""Let installed dvpmvs plugins ship their own Hydra config groups.

A plugin distribution declares an entry point in the group ``dvpmvs.configs`` whose value is an
importable package holding config-group folders, for example::

    [project.entry-points."dvpmvs.configs"]
    my_plugin = "my_plugin.conf"

with ``my_plugin/conf/view_selector/my_selector.yaml``. Its groups are then selectable on the
command line (``view_selector=my_selector``) exactly like the built-in ones, with no change to
dvpmvs itself.
"""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

from dvpmvs.registry import CONFIG_GROUP, entry_points_of


class DvpmvsPluginConfigs(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        for entry_point in entry_points_of(CONFIG_GROUP):
            search_path.append(provider=f"dvpmvs-plugin-{entry_point.name}", path=f"pkg://{entry_point.value}")
