LAYOUTS = {}
def build_intersection(name, seed): raise KeyError(name)
